"""The stages of a run, each a plain function: normals, relighting files, height, mesh, files.

:func:`reconstruct.pipeline.run_capture` calls them in this order; a notebook user can call
them one by one (``docs/tutorial.md``)::

    capture = load_capture("tablet/", options)             # photographs, lights, mask
    result = estimate_normals(capture, options)            # normals (H, W, 3), albedo (H, W)
    albedo_rgb = capture.stack.chroma * result.albedo[..., None]
    mask = resolve_mask(options, capture.mask, albedo_rgb, result.normals)
    surface = integrate_surface(result.normals, mask, options)   # height (H, W)
    mesh, step, decimation = make_mesh(surface, texture, result.normals, options)

``fit_relighting`` writes the files viewers open (``coefficients.ptm``, ``web/``, ``.rti``),
``leave_one_out`` measures the relighting bases, ``write_surface_files`` writes the maps and
meshes.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.corrections import Corrections
from ptmcore.errors import InputError
from ptmcore.lp import LightSet
from ptmcore.png import write_png
from ptmcore.nearlight import typical_distance
from ptmcore.normalmethods import FITS, NORMAL_METHODS
from ptmcore.normals import lambertian_albedo
from ptmcore.bases import CANDIDATES, ENCODINGS, BasisChoice, choose_basis, fit_published
from ptmcore.ptmencoded import EncodedFits
from ptmcore import fit_ptm_encoded, fit_ptm_rgb_encoded, write_ptm
from ptmcore.resources import thread_count
from ptmcore.rtifile import fit_rti_hsh, write_rti_hsh
from reconstruct.calibration.camera import parse_intrinsics
from reconstruct.mesh.grid import GridMesh, grid_mesh
from reconstruct.mesh.obj import write_obj
from reconstruct.mesh.ply import write_ply
from reconstruct.pipeline.capture import Capture, NearLights
from reconstruct.pipeline.options import RunOptions
from reconstruct.pipeline.report import LightModel, PtmSummary
from reconstruct.pipeline.writer import FileWriter
from reconstruct.report import outputs
from reconstruct.report.web import export_openlime, export_relightable
from reconstruct.surface.choose import integrate_with
from reconstruct.surface.flatten import flatten
from reconstruct.surface.segment import foreground_mask

__all__ = [
    "AUTO_MESH_VERTICES",
    "MIN_DETERMINED_FRACTION",
    "NormalsResult",
    "Relighting",
    "Surface",
    "auto_step",
    "basis_stage_rows",
    "estimate_normals",
    "fit_relighting",
    "integrate_surface",
    "leave_one_out",
    "light_model",
    "make_mesh",
    "resolve_mask",
    "web_export",
    "write_height",
    "write_maps",
    "write_meshes",
    "write_surface_files",
]

#: The automatic mesh step keeps meshes at about this many vertices or fewer, which MeshLab,
#: Blender and CloudCompare handle comfortably; the texture keeps full resolution.
AUTO_MESH_VERTICES = 4_000_000

Advance = Callable[[int], None]

#: Normals determined at fewer pixels than this fraction of the object's (its mask's, or the
#: whole frame's) are a failed reconstruction: what it would publish is the plane
#: (0, 0, 1) put where no normal was found. An object filling a thousandth of the frame,
#: with no mask, still passes.
MIN_DETERMINED_FRACTION = 1e-3


@dataclass
class NormalsResult:
    """Unit normals ``(H, W, 3)`` float32, luminance albedo ``(H, W)`` float32 (linear light),
    how many pixels had too few usable photographs to determine a normal, and the reflectance
    lobe fitted with them (:meth:`ptmcore.lobe.Lobe.summary`), if any."""

    normals: np.ndarray
    albedo: np.ndarray
    undetermined: int = 0
    lobe: dict | None = None


def _undetermined(valid: np.ndarray, capture: Capture) -> int:
    """The pixels without a normal (``valid`` false), once it is checked that enough have one.

    Raises
    ------
    InputError
        Naming the capture, when fewer than :data:`MIN_DETERMINED_FRACTION` of the object's
        pixels, or none, have a normal: too few of its photographs light them.
    """
    where = np.ones(valid.shape, bool) if capture.mask is None else capture.mask
    pixels, found = int(np.count_nonzero(where)), int(np.count_nonzero(valid & where))
    if found == 0 or found < MIN_DETERMINED_FRACTION * pixels:
        whose = "the photographs'" if capture.mask is None else "the mask's"
        raise InputError(f"no surface to reconstruct: a normal was determined at {found:,} of {whose} {pixels:,} "
                         "pixels, the others having too few lit, unsaturated photographs (are most photographs dark?)",
                         capture.source)
    return int(np.count_nonzero(~valid))


def estimate_normals(capture: Capture, options: RunOptions | None = None, *,
                     progress: Advance | None = None) -> NormalsResult:
    """Normals and albedo of a capture, by ``options.normals`` and ``options.fit``
    (:data:`ptmcore.normalmethods.NORMAL_METHODS` and ``FITS``).

    Every fit here works on linear light, where a Lambertian surface's shading is n·l; the
    PTM written for viewers is fitted separately (:func:`fit_relighting`), to the photographs
    as encoded.

    Parameters
    ----------
    capture : Capture
        From :func:`reconstruct.pipeline.load_capture`.
    options : RunOptions, optional
        ``normals`` (ps, ptm, ptm-debiased), ``fit`` (lobe, irls, trimmed, plain), ``solver``,
        ``threads``.
    progress : callable, optional
        ``progress(rows)`` as bands of rows are done (H in all).

    Returns
    -------
    NormalsResult

    Raises
    ------
    InputError
        When (nearly) no normal is determined (:data:`MIN_DETERMINED_FRACTION`), or the method
        assumes distant lights and the capture's are near.
    """
    opt = options or RunOptions()
    method = NORMAL_METHODS[opt.normals]
    stack = capture.stack
    if capture.near is not None:
        if method.near is None:
            raise InputError(f"--normals {method.name} assumes distant lights; with near lights "
                             f"use {' or '.join(m.name for m in NORMAL_METHODS.values() if m.near)} "
                             "(or --light-positions none)")
        found = method.near(stack, capture.near.positions, opt.threads, progress)
    else:
        found = method.distant(stack, capture.lights.directions, FITS[opt.fit], opt.solver, opt.threads, progress)
    albedo = found.albedo
    if albedo is None:  # a PTM's normals: the Lambertian albedo under distant lights
        albedo = lambertian_albedo(stack, capture.lights.directions, found.normals, threads=opt.threads)
    return NormalsResult(found.normals, albedo, _undetermined(found.valid, capture), found.lobe)


def resolve_mask(option: Path | str | None, known: np.ndarray | None,
                 albedo_rgb: np.ndarray | Callable[[], np.ndarray],
                 normals: np.ndarray, warnings: list[str] | None = None) -> np.ndarray | None:
    """The mask to integrate on: ``known`` (from the capture), or with ``option == "auto"``
    the object found against its background (:func:`reconstruct.surface.foreground_mask`);
    None (the whole frame) with a warning appended to ``warnings`` where that fails.

    ``albedo_rgb`` may be a function that makes it: it is only needed with ``"auto"``.
    """
    if option != "auto":
        return known
    try:
        return foreground_mask(albedo_rgb() if callable(albedo_rgb) else albedo_rgb, normals)
    except ValueError as exc:
        if warnings is not None:
            warnings.append(f"no automatic mask: {exc}")
        return None


@dataclass
class Relighting:
    """The relighting files written, and what report.json says of them."""

    names: list[str]
    summary: PtmSummary
    warnings: list[str] = field(default_factory=list)


def fit_relighting(lights: LightSet, options: RunOptions, folder: str | os.PathLike, *,
                   progress: Advance | None = None, fits: EncodedFits | None = None,
                   corrections: Corrections | None = None) -> Relighting:
    """Write ``coefficients.ptm`` and, with ``options.hsh``, ``coefficients.rti``.

    The fits are HP's PTMfitter's (its files are reproduced byte for byte) of the photographs
    display-encoded as sRGB (8-bit sRGB photographs as they are; 16-bit and float ones encoded),
    or in linear light (``options.ptm_encoding``). They come from ``fits``, made in the pass that decoded
    the photographs (``Capture.fits``), when those are of these photographs and lights; else
    from a second pass over the files, streamed so that memory stays bounded. With near lights
    these files use each photograph's direction from the image centre.

    Parameters
    ----------
    lights : LightSet
        The photographs and their light directions (``Capture.lights``).
    options : RunOptions
        ``ptm_format``, ``ptm_encoding``, ``linearize``, ``solver``, ``hsh``, ``pixel_size`` (for
        the web viewer's scale), ``threads``.
    folder : path
        Where to write the files.
    progress : callable, optional
        ``progress(k)`` as photographs are read (N in all; at once when ``fits`` are used).
    fits : EncodedFits, optional
        Fits made while decoding (``Capture.fits``). The coefficients used are taken out of it,
        so their memory goes as soon as the files are written.
    corrections : Corrections, optional
        What the decoding pass did to each photograph (``Capture.corrections``), done again
        when the files are read a second time.
    """
    folder = Path(folder)
    paths, directions = lights.paths, lights.directions
    kw = {"solver": options.solver, "threads": options.threads, "progress": progress, "corrections": corrections}
    coded = {"encoding": options.ptm_encoding, "linearize": options.linearize}
    # Fits of other photographs or lights (some dropped after decoding) are not these files'.
    usable = fits is not None and fits.matches(paths, directions, options.solver, options.ptm_encoding)
    made = fits.take_ptm(options.ptm_format) if usable else None
    if made is not None:
        coef8, rgb8 = made
        if progress is not None:
            progress(len(paths))
    elif options.ptm_format == "lrgb":
        coef8, rgb8 = fit_ptm_encoded(paths, directions, **kw, **coded)
    else:
        coef8, rgb8 = fit_ptm_rgb_encoded(paths, directions, **kw, **coded), None
    del made
    written = write_ptm(folder / "coefficients.ptm", coef8, rgb8)
    result = Relighting(["coefficients.ptm"], PtmSummary.from_written(written, options.ptm_encoding))
    del coef8, rgb8
    if options.hsh:
        hsh = fits.take_hsh(3) if usable else None
        if hsh is None:
            hsh = fit_rti_hsh(paths, directions, order=3, threads=options.threads, corrections=corrections, **coded)
        result.summary = PtmSummary.from_written(
            written, options.ptm_encoding, hsh=write_rti_hsh(folder / "coefficients.rti", hsh, order=3))
        result.names.append("coefficients.rti")
        if len(paths) < HSH_MIN_LIGHTS:
            result.warnings.append(
                f"coefficients.rti: an HSH of order 3 has 9 coefficients per channel and {len(paths)} photographs "
                f"leave it loosely held between their lights (relit there it can be far too dark or bright; "
                f"at least {HSH_MIN_LIGHTS} are advised); coefficients.ptm has 6")
    return result


#: Photographs below which the order-3 HSH (9 coefficients) is loosely held between the lights:
#: on a 16-light synthetic tablet it relit half as bright as the photographs midway between
#: lights, and agreed with the PTM with 48 lights; twice its coefficients is the usual margin
#: of a least-squares fit.
HSH_MIN_LIGHTS = 18


def publish_relighting(capture: Capture, options: RunOptions, folder: str | os.PathLike, *,
                       progress: Advance | None = None) -> tuple[list[str], BasisChoice]:
    """Choose the relighting basis (``options.basis``, ``options.basis_encoding``), fit it to
    the stack and write it as ``web/``: OpenLIME's files and the page.

    ``"auto"`` scores every candidate of ``options.basis_candidates`` on the capture by
    leave-one-out error (:func:`ptmcore.bases.choose_basis`); the choice and every score go
    into report.json.

    Returns
    -------
    names : list of str
        The files written, relative to ``folder``.
    choice : BasisChoice
    """
    directions = capture.lights.directions
    candidates = CANDIDATES[options.basis_candidates] if options.basis == "auto" else (options.basis,)
    encodings = ENCODINGS if options.basis_encoding == "auto" else (options.basis_encoding,)
    choice = choose_basis(capture.stack, directions, candidates=candidates, encodings=encodings, mask=capture.mask,
                          threads=options.threads, progress=progress)
    basis = fit_published(capture.stack, directions, choice.name, choice.encoding, threads=options.threads,
                          progress=progress)
    folder = Path(folder)
    written = export_relightable(folder / "web", basis, pixel_size_mm=options.pixel_size)
    return [p.relative_to(folder).as_posix() for p in written], choice


def basis_stage_rows(options: RunOptions, height: int) -> int:
    """The rows :func:`publish_relighting` reports in all: the fit's, and as many again for each
    training of the learned basis it may do (scoring it, fitting it). When auto scores it and
    chooses another basis, the stage ends a third short."""
    if options.basis == "neural":
        return 2 * height
    if options.basis == "auto" and "neural" in CANDIDATES[options.basis_candidates]:
        return 3 * height
    return height


def web_export(folder: Path, coefficients: np.ndarray, rgb: np.ndarray, pixel_size: float | None,
               encoding: str = "srgb") -> list[str]:
    """Write the web page and OpenLIME's files of an LRGB PTM (coefficients in ``encoding``)
    under ``folder/web/``; return their names relative to ``folder``."""
    written = export_openlime(folder / "web", coefficients, rgb, pixel_size_mm=pixel_size, encoding=encoding)
    return [f"web/{p.name}" for p in written]


def leave_one_out(capture: Capture, mask: np.ndarray | None, folder: str | os.PathLike, *,
                  threads: int | None = None, progress: Advance | None = None) -> dict:
    """Leave-one-out relighting error of each basis of luminance: ``loo_<basis>.tif`` maps
    written into ``folder``, their RMS returned.

    PTM and HSH of orders 2 to 4 (order 4 with more than 16 photographs) by their exact
    leave-one-out residuals, RBF and bilinear by interpolating the other photographs
    (:func:`ptmcore.loo.loo_interpolated`). Errors are in 8-bit sRGB levels, which is how the
    differences would look on screen.
    """
    import tifffile

    from ptmcore.images import linear_to_srgb
    from ptmcore.interpolation import DEFAULT_RESOLUTION, bilinear_loo_matrix, default_sigma, rbf_loo_matrix
    from ptmcore.loo import loo_hsh, loo_interpolated, loo_ptm

    def levels(v: np.ndarray) -> np.ndarray:
        return 255.0 * linear_to_srgb(v)

    stack, directions = capture.stack, capture.lights.directions
    sigma = default_sigma(directions)
    bases = {"ptm": lambda **kw: loo_ptm(stack, directions, **kw)}
    for order in (2, 3, 4):
        if len(directions) > order * order:
            bases[f"hsh{order}"] = lambda order=order, **kw: loo_hsh(stack, directions, order, **kw)
    bases["rbf"] = lambda **kw: loo_interpolated(stack, rbf_loo_matrix(directions, sigma), **kw)
    bases["bilinear"] = lambda **kw: loo_interpolated(
        stack, bilinear_loo_matrix(directions, DEFAULT_RESOLUTION, sigma), **kw)
    result = {}
    for name, compute in bases.items():
        rms_map, rms = compute(mask=mask, transform=levels, threads=threads, progress=progress)
        with atomic_write(Path(folder) / f"loo_{name}.tif", "wb") as f:
            tifffile.imwrite(f, rms_map.astype(np.float32), metadata={"unit": "8-bit sRGB levels"})
        result[name] = float(rms)
    return {"rms_levels": result, "best": min(result, key=result.get), "unit": "8-bit sRGB levels"}


def light_model(near: NearLights | None, shape: tuple[int, int], options: RunOptions) -> LightModel:
    """What report.json says of the light model: distant directions or near point lights."""
    if near is None:
        return LightModel("distant", detail="one light direction per photograph")
    return LightModel(
        "near", near.source, typical_distance(near.positions, shape),
        f"each pixel has its own light direction and inverse-square falloff "
        f"({NORMAL_METHODS[options.normals].near_words}); "
        "coefficients.ptm and the other relighting files use the direction from the image centre",
    )


@dataclass
class Surface:
    """A height map ``(H, W)`` float32 (NaN outside the mask), its unit, and how it was integrated."""

    height: np.ndarray
    unit: str
    integrator: str
    reason: str


def integrate_surface(normals: np.ndarray, mask: np.ndarray | None, options: RunOptions) -> Surface:
    """Integrate normals ``(H, W, 3)`` into a height map, then flatten it if asked.

    Orthographic by default (heights in mm with ``options.pixel_size``, else pixels); with
    ``options.intrinsics`` a pinhole camera (mm with ``options.distance``, else depth relative
    to the object's median).
    """
    # RunOptions refuses fc with intrinsics; thread_count, as scipy.fft's -1 would be every CPU.
    camera = None if options.intrinsics is None else parse_intrinsics(options.intrinsics)
    if camera is not None:
        unit = "mm" if options.distance else "relative depth"
    else:
        unit = "mm" if options.pixel_size else "pixel"
    chosen = integrate_with(normals, options.integrator, mask, pixel_size=options.pixel_size or 1.0,
                            intrinsics=camera, distance=options.distance, workers=thread_count(options.threads))
    height = chosen.height
    if options.flatten is not None:
        extra = {"cutoff_px": options.flatten_cutoff} if options.flatten == "highpass" else {}
        height = flatten(height, options.flatten, mask=mask, **extra)
    return Surface(height, unit, chosen.method, chosen.reason)


def auto_step(shape: tuple[int, int], max_vertices: int = AUTO_MESH_VERTICES) -> int:
    """Smallest grid step whose mesh has at most ``max_vertices`` vertices."""
    return max(1, math.ceil(math.sqrt(shape[0] * shape[1] / max_vertices)))


def make_mesh(surface: Surface, texture: np.ndarray, normals: np.ndarray,
              options: RunOptions) -> tuple[GridMesh, int, dict | None]:
    """The textured grid mesh of a surface (``options.step``, else :func:`auto_step`), decimated
    when ``options.decimate`` or ``options.max_error`` asks; returns it, its step, and what the
    decimation reached (None without one)."""
    step = options.step or auto_step(surface.height.shape)
    mesh = grid_mesh(surface.height, texture=texture, step=step, pixel_size=options.pixel_size, normals=normals)
    if len(mesh.faces) == 0:
        h, w = surface.height.shape
        known = int(np.isfinite(surface.height).sum())
        raise InputError(
            f"the mesh would have no triangles: {known} pixel(s) of height on a {w}×{h} image"
            + (f" at a step of {step} pixels (--step)" if step > 1 else "")
            + "; a mesh needs at least 2×2 neighbouring pixels of the object")
    decimation = None
    if options.decimate is not None or options.max_error is not None:
        from reconstruct.mesh.ops import decimate  # open3d and trimesh: a quarter of a second to import

        mesh, decimation = decimate(mesh, target_faces=options.decimate, max_error=options.max_error)
    return mesh, step, decimation


def write_maps(folder: str | os.PathLike, writer: FileWriter, *, normals: np.ndarray, texture: np.ndarray,
               mask: np.ndarray | None) -> list[str]:
    """Start writing ``albedo.png``, ``normals.png``, ``normals.npy`` and ``mask.png`` (when
    there is a mask) with ``writer``; return their names. The arrays must not change until
    the writer is done. Only ``albedo.png`` is tagged as sRGB (:mod:`ptmcore.colourtags`):
    the normal map and the mask are data."""
    folder = Path(folder)
    names = writer.submit(["normals.png"], outputs.write_normals_png, folder / "normals.png", normals)
    names += writer.submit(["albedo.png"], write_png, folder / "albedo.png", texture, srgb=True)
    names += writer.submit(["normals.npy"], outputs.write_npy, folder / "normals.npy", normals)
    if mask is not None:
        names += writer.submit(["mask.png"], lambda: write_png(folder / "mask.png", mask.astype(np.uint8) * 255))
    return names


def write_height(folder: str | os.PathLike, writer: FileWriter, surface: Surface, options: RunOptions) -> list[str]:
    """Start writing ``height.tif`` with ``writer``; return its name."""
    return writer.submit(["height.tif"], outputs.write_height_tiff, Path(folder) / "height.tif", surface.height,
                         surface.unit, options.pixel_size)


def write_meshes(folder: str | os.PathLike, writer: FileWriter, mesh: GridMesh, texture: np.ndarray,
                 options: RunOptions) -> list[str]:
    """Start writing ``mesh.obj`` (with ``mesh.mtl`` and ``mesh_texture.png``), ``mesh.ply``,
    and ``mesh.glb`` / ``solid.stl`` when ``options`` asks, with ``writer``; return their
    names. The OBJ's texture is a copy of ``albedo.png`` when this writer writes it
    (:func:`write_maps`) or it is there already, else ``texture`` encoded again."""
    folder = Path(folder)
    albedo = folder / "albedo.png"
    copy = "albedo.png" in writer.names or albedo.is_file()
    # Longest first: the writer's threads take jobs in order.
    names = writer.submit(["mesh.obj", "mesh.mtl", "mesh_texture.png"],
                          lambda: write_obj(folder / "mesh.obj", mesh, _written(writer, albedo) if copy else texture))
    names += writer.submit(["mesh.ply"], write_ply, folder / "mesh.ply", mesh, texture_file="mesh_texture.png")
    if options.glb or options.solid is not None:
        from reconstruct.mesh.ops import solid, write_glb, write_stl  # trimesh: imported only when used
    if options.glb:
        names += writer.submit(["mesh.glb"], write_glb, folder / "mesh.glb", mesh, texture)
    if options.solid is not None:
        names += writer.submit(["solid.stl"], lambda: write_stl(folder / "solid.stl", solid(mesh, options.solid)))
    return names


def _written(writer: FileWriter, path: Path) -> Path:
    """``path`` once the writer has written it. Called in a job of the same writer, which is
    safe for a file submitted earlier: a worker has taken its job by then (they take jobs in
    order, and a job taken is never cancelled)."""
    writer.wait_for(path.name)
    return path


def write_surface_files(folder: str | os.PathLike, *, normals: np.ndarray, texture: np.ndarray,
                        surface: Surface, mesh: GridMesh, mask: np.ndarray | None,
                        options: RunOptions) -> list[str]:
    """Write the maps and meshes every run has (README, "Output folder"); return their names.

    ``albedo.png``, ``normals.png``, ``normals.npy``, ``height.tif``, ``mesh.ply``,
    ``mesh.obj`` (with ``mesh.mtl`` and ``mesh_texture.png``), ``mask.png`` when there is a
    mask, ``mesh.glb`` with ``options.glb``, ``solid.stl`` with ``options.solid``. They are
    written in parallel threads; a run starts each group as soon as its data exists instead
    (:func:`write_maps`, :func:`write_height`, :func:`write_meshes` with a
    :class:`reconstruct.pipeline.writer.FileWriter`).
    """
    with FileWriter(options.threads) as writer:
        write_maps(folder, writer, normals=normals, texture=texture, mask=mask)
        write_height(folder, writer, surface, options)
        write_meshes(folder, writer, mesh, texture, options)
        return writer.wait()
