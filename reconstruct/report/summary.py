"""What ``report.html`` says in words: the summary of a run, and what each output file is.

``report.json`` keeps the machine's names (``fit``, ``integrator``, ``height_rmse_mm``); a
conservator reading the page needs the object's size and relief in millimetres, how the
surface was made and how good it is. These functions turn the report's values (and the height
map's subsample, for the size and relief) into short sentences, and name the files a folder
holds with the programs that open them.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptmcore.normalmethods import FITS, NORMAL_METHODS

__all__ = ["FileEntry", "Extent", "extent", "file_entries", "summary_rows", "unit_words"]

_INTEGRATORS = {
    "masked": "least squares on the object only",
    "bilateral": "bilateral integration, keeping steps sharp (Cao et al. 2022)",
    "dct": "least squares over the whole frame (DCT)",
    "fc": "Frankot–Chellappa (Fourier)",
}
_FLATTEN = {"plane": "a plane", "poly2": "a quadratic surface", "poly3": "a cubic surface",
            "highpass": "a high-pass filter"}

_VIEWERS_3D = "MeshLab, CloudCompare or Blender"
_IMAGE = "any image viewer"
#: What each file of an output folder is, and how to open it: (name, what, how).
_FILES: tuple[tuple[str, str, str], ...] = (
    ("coefficients.ptm", "Polynomial Texture Map (HP PTM 1.2) for interactive relighting",
     "RTIViewer (Cultural Heritage Imaging); reconstruct relight or reconstruct preview"),
    ("coefficients.rti", "hemispherical-harmonics RTI (order 3)", "RTIViewer"),
    ("web/index.html", "web page relighting the PTM (copy the web/ folder to any web server)", "a web browser"),
    ("web/info.json", "the PTM for the OpenLIME web viewer (with plane_0–2.jpg)", "OpenLIME on a web server"),
    ("mesh.ply", "textured 3D mesh (binary PLY, vertex colours)", _VIEWERS_3D),
    ("mesh.obj", "the same mesh as OBJ, with mesh.mtl and mesh_texture.png (keep the three together)",
     _VIEWERS_3D),
    ("mesh.mtl", "the OBJ's material", "opened with mesh.obj"),
    ("mesh_texture.png", "the OBJ's texture (8-bit sRGB)", f"opened with mesh.obj; {_IMAGE}"),
    ("mesh.glb", "binary glTF mesh with its texture", "Blender, any glTF viewer or web browser viewer"),
    ("solid.stl", "watertight solid (relief on a base) for 3D printing", "a slicer (PrusaSlicer, Cura), MeshLab"),
    ("height.tif", "height map, 32-bit float TIFF, empty (NaN) outside the object", "ImageJ/Fiji, QGIS; Python tifffile"),
    ("normals.png", "normal map, 16-bit PNG (R = x right, G = y up, B = z towards the camera)",
     f"{_IMAGE}; Blender as a normal map"),
    ("normals.npy", "unit normals, float32 array (H × W × 3)", "Python: numpy.load"),
    ("albedo.png", "surface colour without shading (8-bit sRGB)", _IMAGE),
    ("mask.png", "the object's outline used (white = object)", _IMAGE),
    ("loo_ptm.tif", "leave-one-out relighting error of the PTM per pixel", "ImageJ/Fiji"),
    ("loo_hsh2.tif", "leave-one-out relighting error of HSH order 2 per pixel", "ImageJ/Fiji"),
    ("loo_hsh3.tif", "leave-one-out relighting error of HSH order 3 per pixel", "ImageJ/Fiji"),
    ("lights.lp", "the light directions used (RTIBuilder's .lp format)", "a text editor; RTIBuilder"),
    ("light_positions.csv", "the near lights' positions (pixels)", "a spreadsheet"),
    ("distances.ply", "the scan coloured by its distance to the reconstruction", _VIEWERS_3D),
    ("histogram.png", "histogram of the scan's distances", _IMAGE),
    ("overlay.png", "the aligned scan and reconstruction, and the distance map", _IMAGE),
    ("comparison.json", "the comparison with the scan, every number", "a text editor; Python json"),
    ("report.json", "every number of the run (inputs, options, timings, accuracy)", "a text editor; Python json"),
    ("report.html", "this page", "a web browser"),
)


@dataclass(frozen=True)
class FileEntry:
    """One output file as the page lists it: ``name`` (relative to the folder, a link)."""

    name: str
    what: str
    how: str


@dataclass(frozen=True)
class Extent:
    """The size of what a height map covers and the depth of its relief.

    Attributes
    ----------
    width, height : float
        Extent of the object (its finite heights' bounding box) in ``unit``.
    depth : float or None
        Relief depth: the 0.5th to 99.5th percentile of the heights, in the heights' unit
        (None without finite heights).
    unit : str
        ``mm`` when a pixel size is known, else ``pixels``.
    whole_frame : bool
        Whether the heights fill the frame (no mask).
    """

    width: float
    height: float
    depth: float | None
    unit: str
    whole_frame: bool


def extent(height: np.ndarray, stride: int, pixel_size: float | None) -> Extent:
    """The object's extent and relief depth from a subsample of its height map.

    Parameters
    ----------
    height : ndarray, shape (h, w)
        Every ``stride``-th height of the full map, NaN outside the object.
    stride : int
        The subsample's step in full-size pixels.
    pixel_size : float or None
        Millimetres per full-size pixel, or None (extent in pixels).
    """
    finite = np.isfinite(height)
    rows, cols = np.flatnonzero(finite.any(axis=1)), np.flatnonzero(finite.any(axis=0))
    per = (pixel_size or 1.0) * stride
    unit = "mm" if pixel_size else "pixels"
    if rows.size == 0:
        return Extent(height.shape[1] * per, height.shape[0] * per, None, unit, True)
    lo, hi = np.percentile(height[finite], [0.5, 99.5])
    return Extent(float(cols[-1] - cols[0] + 1) * per, float(rows[-1] - rows[0] + 1) * per, float(hi - lo), unit,
                  bool(finite.all()))


def _num(x: float, digits: int = 3) -> str:
    return f"{x:.{digits}g}" if abs(x) < 10 ** digits else f"{x:,.0f}"


def _method(report: dict) -> str:
    params = report.get("parameters") or {}
    inputs = report.get("inputs") or {}
    if "normal_map" in inputs:
        normals = f"from the normal map {Path(inputs['normal_map']).name} (made elsewhere)"
    elif "ptm" in inputs and "photographs" not in inputs:
        normals = f"from the maximum of each pixel's polynomial in {Path(inputs['ptm']).name}"
    else:
        method = NORMAL_METHODS.get(params.get("normals", "ps"))
        fit = params.get("fit", "lobe")
        how = FITS[fit].words if fit in FITS else fit
        if fit == "lobe" and not report.get("reflectance_lobe"):
            how = "robust Lambertian fit (no glossy lobe needed)"
        normals = method.words.format(fit=how) if method else f"by {params.get('normals')}"
    mesh = report.get("mesh") or {}
    integrator = mesh.get("integrator")
    surface = _INTEGRATORS.get(integrator, integrator or "?")
    if mesh.get("integrator_reason"):
        surface += f" ({mesh['integrator_reason']})"
    text = f"Normals {normals}. Surface integrated by {surface}."
    if params.get("flatten"):
        text += f" Low-frequency bending removed with {_FLATTEN.get(params['flatten'], params['flatten'])}."
    if params.get("intrinsics"):
        text += " Perspective camera."
    return text


def _photographs(inputs: dict) -> str | None:
    if "photographs" not in inputs:
        return None
    depth = inputs.get("bit_depth")
    return (f"{inputs['photographs']} photographs" + (f", {depth}-bit" if depth else "")
            + f", {inputs.get('width')} × {inputs.get('height')} pixels")


def _accuracy(report: dict) -> str | None:
    acc = report.get("accuracy") or {}
    parts = []
    normals = acc.get("normals") or {}
    if normals.get("mean_deg") is not None:
        parts.append(f"normals within {normals['mean_deg']:.2f}° on average ({normals.get('median_deg', float('nan')):.2f}° "
                     f"median) of the ground truth")
    if acc.get("height_rmse_mm") is not None:
        parts.append(f"heights {acc['height_rmse_mm']:.3g} mm RMS from it")
    return "; ".join(parts) + "." if parts else None


def _scan(comparison: dict) -> str | None:
    stats = comparison.get("statistics_mm") or {}
    if stats.get("rms") is None:
        return None
    text = (f"against the laser scan {Path(comparison.get('scan', '')).name}: RMS distance {stats['rms']:.3g} mm, "
            f"95% of the scan within {stats.get('p95_abs', float('nan')):.3g} mm "
            f"({stats.get('count', 0):,} scan points, {stats.get('overlap_fraction', 0):.0%} overlapping)")
    tol = comparison.get("tolerance") or {}
    if tol:
        verdict = "passed" if tol.get("passed") else "FAILED"
        text += (f"; tolerance {tol.get('tolerance_mm')} mm {verdict} "
                 f"({tol.get('fraction_within', 0):.1%} within, {tol.get('min_fraction', 0):.0%} required)")
    return text + "."


def unit_words(unit: str) -> str:
    """A unit as a sentence or a label says it: report.json's ``"pixel"`` is ``"pixels"``;
    ``"mm"`` and the others are said as they are written."""
    return "pixels" if unit == "pixel" else unit


def summary_rows(report: dict | None, comparison: dict | None, size: Extent | None, *,
                 object_name: str) -> list[tuple[str, str]]:
    """The summary table of ``report.html``: (label, sentence) rows in reading order.

    Parameters
    ----------
    report, comparison : dict or None
        ``report.json`` and ``comparison.json``.
    size : Extent or None
        The object's extent and relief (:func:`extent`), when a height map is known.
    object_name : str
        The capture's name.
    """
    rows = [("Object", object_name)]
    report = report or {}
    inputs = report.get("inputs") or {}
    photos = _photographs(inputs)
    if photos:
        rows.append(("Photographs", photos))
    if size is not None:
        where = "the whole frame" if size.whole_frame else "the object's outline"
        rows.append(("Size", f"{_num(size.width)} × {_num(size.height)} {size.unit} ({where})"))
        if size.depth is not None:
            unit = unit_words(report.get("height_unit", size.unit))
            rows.append(("Relief depth", f"{_num(size.depth)} {unit} (lowest to highest point, "
                                         "leaving out the extreme 0.5% at each end)"))
    elif "width" in inputs:
        rows.append(("Size", f"{inputs['width']} × {inputs['height']} pixels"))
    pixel = (report.get("parameters") or {}).get("pixel_size")
    rows.append(("Scale", f"{_num(pixel, 4)} mm per pixel" if pixel else
                 "no pixel size given: lengths and heights in pixels (give --pixel-size for millimetres)"))
    if report:
        rows.append(("Method", _method(report)))
    accuracy = [a for a in (_accuracy(report), _scan(comparison or {})) if a]
    if accuracy:
        rows.append(("Accuracy", " ".join(a[0].upper() + a[1:] for a in accuracy)))
    elif report:
        rows.append(("Accuracy", "not measured (no ground truth or scan given)"))
    return rows


def _describe(name: str) -> tuple[str, str]:
    for known, what, how in _FILES:
        if known == name:
            return what, how
    return "written by the run", "—"


def file_entries(folder: str | os.PathLike, also_written: Iterable[str] = ()) -> list[FileEntry]:
    """The files of an output folder, each with what it is and how to open it.

    Parameters
    ----------
    folder : path
        The output folder (or the staging folder it is being written in).
    also_written : iterable of str
        Names written after the page (``report.json``, ``comparison.json``, ``report.html``
        itself) or while it is made, listed even though they are not there yet.

    Returns
    -------
    list of FileEntry
        In the order of :data:`_FILES` (the viewer files first), unknown files last; hidden
        files (temporary stacks, locks) are left out. ``web/`` is one entry: its page when it
        has one, else its ``info.json``.
    """
    folder = Path(folder)
    present = {p.name for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")}
    also = set(also_written)
    present |= {n for n in also if "/" not in n}  # web/ is one entry, below
    web = folder / "web"
    if (web / "index.html").is_file() or "web/index.html" in also:
        present.add("web/index.html")
    elif (web / "info.json").is_file() or "web/info.json" in also:
        present.add("web/info.json")
    order = {name: k for k, (name, _, _) in enumerate(_FILES)}
    names = sorted(present, key=lambda n: (order.get(n, len(order)), n))
    return [FileEntry(n, *_describe(n)) for n in names]
