"""The whole reconstruction of one capture: photographs → PTM → normals → height → mesh.

:func:`run` is what ``reconstruct run`` calls: :func:`run_capture` for photographs and their
``.lp`` file, :func:`run_ptm` for an existing ``.ptm`` file. Each step is also a plain function
that a notebook user can call alone (:func:`ptmcore.load_stack`, :func:`ptmcore.fit_ptm`,
:func:`ptmcore.photometric_stereo`, :func:`ptmcore.ptmfile.fit_ptm_encoded`,
:func:`reconstruct.surface.integrate.integrate`, :func:`reconstruct.mesh.grid.grid_mesh`, ...).

Output folder layout (stable; later versions add files, never rename them)::

    coefficients.ptm   the PTM, HP PTM 1.2 (LRGB or RGB), as HP's PTMfitter fits it
    web/               info.json and plane_0..2.jpg for the OpenLIME web viewer (LRGB)
    normals.npy        H×W×3 float32 unit normals (x right, y up, z towards the camera)
    normals.png        16-bit RGB normal map, OpenGL convention (R=x, G=y, B=z)
    albedo.png         8-bit sRGB albedo
    height.tif         float32 height map, NaN outside the mask; unit in report.json
    mesh.ply           binary PLY: vertex colours, texture coordinates, normals
    mesh.obj           OBJ with mesh.mtl and mesh_texture.png
    mask.png           the mask used (when one was given or found)
    coefficients.rti   with --hsh: HSH of order 3 (RTIViewer's .rti)
    solid.stl          with --solid: watertight relief on a base, for 3D printing
    mesh.glb           with --glb: binary glTF with the texture
    loo_*.tif          with --loo: leave-one-out relighting error of each basis
    light_positions.csv  with near lights: the light positions used (pixels)
    report.json        inputs, parameters, versions, stage times and memory, warnings, accuracy
    report.html        self-contained page: inputs, photographs, relit renderings, maps, mesh
"""

from __future__ import annotations

import math
import os
import platform
import shutil
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

import ptmcore
from ptmcore.atomic import atomic_write
from ptmcore.errors import InputError
from ptmcore.fit import fit_ptm
from ptmcore.images import LUMA_WEIGHTS, ImageStack, load_stack, read_image, write_png
from ptmcore.intensity import apply_intensities, estimate_intensities, read_intensities
from ptmcore.lp import LightSet, read_lp
from ptmcore.nearlight import (
    fit_ptm_near,
    near_lambertian_albedo,
    near_photometric_stereo,
    read_light_positions,
    typical_distance,
    write_light_positions,
)
from ptmcore.normals import lambertian_albedo, normals_from_ptm, photometric_stereo
from ptmcore.psdataset import is_ps_dataset, read_ps_dataset
from ptmcore.ptmfile import fit_ptm_encoded, fit_ptm_rgb_encoded, read_ptm, write_ptm
from ptmcore.robust import (
    debiased_normals,
    hemisphere_coefficients,
    robust_photometric_stereo,
    robust_ptm,
)
from ptmcore.rtifile import fit_rti_hsh, write_rti_hsh
from ptmcore.solvers import analyse_lights

from reconstruct.report import outputs
from reconstruct.surface.accuracy import GroundTruth, height_rmse, load_ground_truth, normal_accuracy
from reconstruct.surface.flatten import flatten
from reconstruct.surface.integrate import integrate
from reconstruct.mesh.grid import grid_mesh
from reconstruct.mesh.obj import write_obj
from reconstruct.mesh.ply import write_ply
from reconstruct.mesh.ops import decimate, solid, write_glb, write_stl
from reconstruct.surface.normalmaps import read_normal_map, shaded
from reconstruct.calibration.camera import parse_intrinsics
from reconstruct.surface.perspective import integrate_perspective
from reconstruct.pipeline.profiling import StageTimer
from reconstruct.report.html import write_report_html
from reconstruct.surface.segment import foreground_mask
from reconstruct.report.web import export_openlime

#: Normal methods; the default is the more accurate on the synthetic benchmark (BENCHMARKS.md).
NORMAL_METHODS = ("ps", "ptm", "ptm-debiased")
#: Per-pixel fits; the default is the more accurate on the synthetic benchmark with specular
#: highlights and shadows (BENCHMARKS.md), at about three times the plain fit's time.
FITS = ("irls", "trimmed", "plain")
PTM_FORMATS = ("lrgb", "rgb")
SOLVERS = ("pinv", "lstsq", "rohde")
FLATTENINGS = ("plane", "poly2", "poly3", "highpass")
INTEGRATORS = ("auto", "dct", "fc", "masked", "bilateral")
#: The automatic mesh step keeps meshes at about this many vertices or fewer, which MeshLab,
#: Blender and CloudCompare handle comfortably; the texture keeps full resolution.
AUTO_MESH_VERTICES = 4_000_000

ProgressFn = Callable[[str, int, int], None]


@dataclass
class RunOptions:
    """Parameters of :func:`run_capture`.

    Attributes
    ----------
    lp : Path or None
        The light file; default: the single ``.lp`` file in the capture folder.
    pixel_size : float or None
        Millimetres per pixel; heights and meshes are in millimetres when given, else in pixels.
    normals : {"ps", "ptm", "ptm-debiased"}
        Photometric stereo; the maximum of each pixel's PTM polynomial (closed form, or on the
        unit circle where it has no interior maximum); or that maximum read through the fit's
        own model of the hemisphere, which removes the PTM's bias towards the view direction.
    fit : {"irls", "trimmed", "plain"}
        How each pixel's samples are weighted: robustly (Tukey IRLS, or 0/1 trimming, leaving
        out shadowed, clipped and specular samples) or by plain least squares.
    integrator : {"auto", "dct", "fc", "masked", "bilateral"}
        Least squares on the mask only ("masked", conjugate gradients preconditioned by the
        bounding box's DCT solver), the same with bilateral weights that keep steps sharp
        ("bilateral"), Poisson with Neumann boundary by DCT on the whole frame ("dct"), or
        Frankot–Chellappa. "auto": masked when a mask is known, else dct.
    step : int or None
        Mesh subsampling; None picks the smallest step that keeps the mesh under
        :data:`AUTO_MESH_VERTICES` vertices.
    linearize : bool
        Take 8-bit photographs as sRGB and linearise them (for the normals; the ``.ptm`` file
        is always fitted to the photographs as they are encoded, as viewers expect).
    ptm_format : {"lrgb", "rgb"}
        Format of ``coefficients.ptm``: one luminance polynomial and a colour per pixel, or
        one polynomial per channel.
    solver : {"pinv", "lstsq", "rohde"}
        The {1}-inverse of the PTM light matrix (ptmcore.solvers); pinv gives the
        least-squares, minimum-norm fit.
    flatten : {"plane", "poly2", "poly3", "highpass"} or None
        Remove low-frequency bending of the height map (from errors in the light directions):
        a plane, a polynomial of order 2 or 3, or wavelengths above ``flatten_cutoff`` pixels.
    flatten_cutoff : float
        For ``flatten="highpass"``: the wavelength in pixels that keeps half its amplitude.
    decimate, max_error : int or float, optional
        Reduce the meshes by quadric edge collapse to this many triangles, or to the fewest
        whose geometric error stays under ``max_error`` (in the height unit); the error
        reached goes into report.json.
    solid : float, optional
        Also write ``solid.stl``: the relief on a base this thick (height unit), closed by
        walls, watertight, for 3D printing.
    glb : bool
        Also write ``mesh.glb`` (binary glTF with the texture) for the web and Blender.
    intrinsics : str, optional
        A perspective (pinhole) camera, ``"fx,fy,cx,cy"`` in pixels, for short lenses; the
        default is orthographic. Heights are then in millimetres when ``distance`` (the camera's
        distance to the object, mm) is given, else relative to the object's median depth.
    distance : float, optional
        See ``intrinsics``.
    hsh : bool
        Also write ``coefficients.rti``: hemispherical harmonics of order 3, RTIViewer's HSH
        format, fitted per channel to the photographs as encoded.
    intensities : str or None
        Per-photograph light intensities: a file (one value or ``r g b`` per photograph, in
        ``.lp`` order) or ``"estimate"`` to estimate them from the photographs; each
        photograph is divided by its light's intensity before the normals are estimated.
    loo : bool
        Measure how well each relighting basis (PTM, HSH of orders 2 and 3) predicts every
        photograph left out of its fit: ``loo_<basis>.tif`` maps and their RMS in report.json.
    mask : Path, "auto" or None
        Image whose non-zero pixels are the object, or ``"auto"`` to segment the object from
        its albedo and normals (:func:`reconstruct.surface.segment.foreground_mask`); height and mesh
        are restricted to it.
    threads : int or None
        Decoding threads (default: all CPUs).
    ground_truth : Path or None
        Folder with ``normals.npy`` (and ``mask.png``, ``height.npy``) to measure accuracy;
        default: ``CAPTURE/ground_truth`` when it exists.
    light_positions : Path, "auto" or "none"
        Near (point) lights: a light-position file (``name,x,y,z`` in pixels,
        :func:`ptmcore.nearlight.read_light_positions`) whose positions give every pixel its
        own light direction and inverse-square falloff. ``"auto"``: the file
        ``light_positions.csv`` beside the ``.lp`` when there is one, or, for a capture
        calibrated from two or more spheres, the lights triangulated from their highlights
        when they are near (:func:`reconstruct.calibration.triangulate.lights_are_near`). ``"none"``:
        distant lights, one direction per photograph.
    """

    lp: Path | None = None
    pixel_size: float | None = None
    normals: str = "ps"
    integrator: str = "auto"
    step: int | None = None
    linearize: bool = True
    ptm_format: str = "lrgb"
    solver: str = "pinv"
    loo: bool = False
    fit: str = "irls"
    hsh: bool = False
    flatten: str | None = None
    decimate: int | None = None
    max_error: float | None = None
    solid: float | None = None
    glb: bool = False
    intrinsics: str | None = None
    distance: float | None = None
    flatten_cutoff: float = 200.0
    intensities: str | None = None
    mask: Path | None = None
    threads: int | None = None
    ground_truth: Path | None = None
    light_positions: Path | str = "auto"


@dataclass
class RunResult:
    """What :func:`run_capture` produced: the output folder, its files and the report."""

    output: Path
    files: dict[str, Path]
    report: dict = field(default_factory=dict)


def find_lp(capture: Path, lp: Path | None = None) -> Path:
    """The light file of a capture: ``lp`` if given, the capture itself if it is an ``.lp``
    file, else the single ``.lp`` file in the capture folder."""
    if lp is not None:
        return Path(lp)
    capture = Path(capture)
    if capture.is_file():
        if capture.suffix.lower() == ".lp":
            return capture
        raise InputError("not a capture folder or .lp file", capture)
    if not capture.is_dir():
        raise InputError("capture folder not found", capture)
    found = sorted(p for p in capture.iterdir() if p.suffix.lower() == ".lp" and p.is_file())
    if not found:
        raise InputError("no .lp light file in the capture folder (give one with --lp)", capture)
    if len(found) > 1:
        names = ", ".join(p.name for p in found)
        raise InputError(f"several .lp files ({names}); choose one with --lp", capture)
    return found[0]


IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")


def capture_images(folder: str | os.PathLike) -> list[Path]:
    """The photographs of a capture folder, in name order."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("capture folder not found", folder)
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not paths:
        raise InputError("no photographs (JPEG, PNG or TIFF) in the capture folder", folder)
    return paths


@dataclass
class NearLights:
    """Point lights of a capture: positions (pixels, project frame) and where they came from."""

    positions: np.ndarray
    source: str


def _calibrate_from_spheres(
    stack: ImageStack, capture: Path, warnings: list[str], opt: RunOptions
) -> tuple[ImageStack, LightSet, np.ndarray, NearLights | None]:
    """Lights read from the glossy spheres of a decoded capture that has no .lp file.

    Returns the stack of the photographs with a usable light, their lights, a mask that leaves
    the spheres out of the reconstruction, and the lights' positions when two or more spheres
    show them to be near (then every triangulated photograph is kept, even where the spheres'
    distant directions disagree, as they must for a near light).
    """
    from reconstruct.calibration.calibrate import calibration_camera
    from reconstruct.calibration.triangulate import sphere_lights

    camera = calibration_camera(stack.paths[0], stack.shape, intrinsics=opt.intrinsics)
    try:
        found = sphere_lights(stack, intrinsics=camera, near=str(opt.light_positions) == "auto")
    except InputError as exc:
        raise InputError(
            f"no .lp light file (give one with --lp), and no light directions from spheres either: {exc.problem}",
            capture,
        ) from None
    result = found.calibration
    rows, cols = np.ogrid[0 : stack.shape[0], 0 : stack.shape[1]]
    keep = np.ones(stack.shape, bool)
    for cx, cy, r in result.spheres:
        # A margin of a few pixels keeps the spheres' dark rims out too.
        keep &= (cols - cx) ** 2 + (rows - cy) ** 2 > (r + 3) ** 2
    warnings.extend(f"{line}; left out" for line in found.left_out)
    usable = found.usable
    if usable.sum() < 3:
        what = "a triangulated light position" if found.positions is not None else "a usable sphere highlight"
        raise InputError(f"fewer than 3 photographs have {what}", capture)
    stack = stack.select(usable)
    if found.positions is not None:
        near = NearLights(found.positions, f"triangulated from {len(result.spheres)} spheres")
        warnings.append(
            f"no .lp file: near lights triangulated from {len(result.spheres)} spheres for "
            f"{int(usable.sum())} of {len(usable)} photographs; each pixel has its own light direction"
        )
        return stack, LightSet(stack.paths, found.directions, None), keep, near
    warnings.append(f"no .lp file: light directions read from {len(result.spheres)} sphere(s) "
                    f"for {int(usable.sum())} of {len(usable)} photographs ({result.view_model} view)")
    return stack, LightSet(stack.paths, found.directions, None), keep, None


def _near_lights_from_file(lights: LightSet, lp_path: Path, option: Path | str) -> NearLights | None:
    """Positions for the photographs of ``lights`` from a light-position file, if there is one.

    With ``"auto"`` the file is ``light_positions.csv`` beside the ``.lp``; photographs are
    matched by file name, and every photograph of the ``.lp`` needs a position.
    """
    if str(option) == "none":
        return None
    path = lp_path.parent / "light_positions.csv" if str(option) == "auto" else Path(option)
    if str(option) == "auto" and not path.is_file():
        return None
    names, positions = read_light_positions(path)
    by_name = dict(zip(names, positions))
    missing = [p.name for p in lights.paths if p.name not in by_name]
    if missing:
        raise InputError(f"no light position for {missing[0]}"
                         + (f" and {len(missing) - 1} more photograph(s)" if len(missing) > 1 else ""), path)
    return NearLights(np.array([by_name[p.name] for p in lights.paths]), str(path))


def read_mask(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """Read a mask image (non-zero = object) and check it matches the photographs."""
    m = read_image(path)
    if m.ndim == 3:
        m = m.max(axis=2)
    if m.shape != shape:
        raise InputError(f"mask is {m.shape[1]}×{m.shape[0]} but the photographs are {shape[1]}×{shape[0]}", path)
    m = m > 0
    if not m.any():
        raise InputError("mask is empty (no non-zero pixel)", path)
    return m


def auto_step(shape: tuple[int, int], max_vertices: int = AUTO_MESH_VERTICES) -> int:
    """Smallest grid step whose mesh has at most ``max_vertices`` vertices."""
    return max(1, math.ceil(math.sqrt(shape[0] * shape[1] / max_vertices)))


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {"python": platform.python_version(), "ptm-reconstruct": ptmcore.__version__}
    for pkg in ("numpy", "scipy", "simplejpeg", "opencv-python-headless", "tifffile", "trimesh"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    return out


def _prepare_output(out: Path) -> Path:
    """Create the output folder and a staging folder inside it; fail early if unwritable."""
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        staging = out / f".partial-{os.getpid()}"
        staging.mkdir(exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot write the output folder ({exc.strerror})", out) from None
    return staging


class _Stages:
    """Times the stages of one run and reports their progress."""

    def __init__(self, progress: ProgressFn | None) -> None:
        self.timer = StageTimer()
        self.progress = progress

    @contextmanager
    def __call__(self, name: str, total: int = 1) -> Iterator[Callable[[int], None]]:
        """Time a stage; stages without steps of their own show 0/1 then 1/1."""
        done = [0]

        def advance(k: int) -> None:
            done[0] += k
            if self.progress is not None:
                self.progress(name, done[0], total)

        if self.progress is not None:
            self.progress(name, 0, total)
        with self.timer.stage(name):
            yield advance
        if done[0] < total:
            advance(total - done[0])


def _integrator(choice: str, mask: np.ndarray | None) -> tuple[str, str]:
    """The integrator to use and why (``auto`` decides by whether the object's outline is known)."""
    if choice != "auto":
        return choice, "chosen"
    if mask is not None:
        return "masked", "a mask is known: least squares on the object only, so its outline does not bend it"
    return "dct", "no mask: least squares on the whole frame with a free boundary"


def _auto_mask(albedo: np.ndarray, normals: np.ndarray, warnings: list[str]) -> np.ndarray | None:
    """The object found against its background, or None (whole frame) with a warning."""
    try:
        return foreground_mask(albedo, normals)
    except ValueError as exc:
        warnings.append(f"no automatic mask: {exc}")
        return None


def _mask_source(option: Path | str | None, mask: np.ndarray | None) -> str | None:
    """How report.json describes the mask used."""
    if str(option) == "auto":
        return "automatic" if mask is not None else "automatic (failed: whole frame)"
    return str(option) if option else None


def _check_options(opt: RunOptions) -> None:
    if opt.normals not in NORMAL_METHODS:
        raise InputError(f"unknown normal method {opt.normals!r}; choose from {', '.join(NORMAL_METHODS)}")
    if opt.integrator not in INTEGRATORS:
        raise InputError(f"unknown integrator {opt.integrator!r}; choose from {', '.join(INTEGRATORS)}")
    if opt.pixel_size is not None and not (math.isfinite(opt.pixel_size) and opt.pixel_size > 0):
        raise InputError(f"pixel size must be a positive number of millimetres, got {opt.pixel_size}")
    if opt.step is not None and opt.step < 1:
        raise InputError(f"mesh step must be at least 1, got {opt.step}")
    if opt.decimate is not None and opt.max_error is not None:
        raise InputError("give either a triangle count to decimate to or a maximum error, not both")
    if opt.solid is not None and not (math.isfinite(opt.solid) and opt.solid > 0):
        raise InputError(f"the solid's base thickness must be positive, got {opt.solid}")
    if opt.intrinsics is not None:
        try:
            parse_intrinsics(opt.intrinsics)
        except ValueError as exc:
            raise InputError(f"--intrinsics: {exc}") from None
    if opt.distance is not None and not (math.isfinite(opt.distance) and opt.distance > 0):
        raise InputError(f"the camera distance must be a positive number of millimetres, got {opt.distance}")
    if opt.flatten is not None and opt.flatten not in FLATTENINGS:
        raise InputError(f"unknown flattening {opt.flatten!r}; choose from {', '.join(FLATTENINGS)}")
    if opt.fit not in FITS:
        raise InputError(f"unknown fit {opt.fit!r}; choose from {', '.join(FITS)}")
    if opt.solver not in SOLVERS:
        raise InputError(f"unknown solver {opt.solver!r}; choose from {', '.join(SOLVERS)}")
    if opt.ptm_format not in PTM_FORMATS:
        raise InputError(f"unknown PTM format {opt.ptm_format!r}; choose from {', '.join(PTM_FORMATS)}")


def _web_export(staging: Path, coefficients: np.ndarray, rgb: np.ndarray, pixel_size: float | None) -> list[str]:
    """Write the OpenLIME web viewer's files under ``web/``; return their names."""
    written = export_openlime(staging / "web", coefficients, rgb, pixel_size_mm=pixel_size)
    return [f"web/{p.name}" for p in written]


def _surface_and_files(
    normals: np.ndarray,
    texture: np.ndarray,
    mask: np.ndarray | None,
    opt: RunOptions,
    staging: Path,
    stage: _Stages,
) -> tuple[np.ndarray, dict, list[str]]:
    """Integrate, mesh and write the files every run has; return height, mesh facts, file names."""
    h, w = normals.shape[:2]
    method, why = _integrator(opt.integrator, mask)
    with stage("integrate"):
        if opt.intrinsics is not None:
            if method not in ("masked", "dct"):
                raise InputError(f"a perspective camera integrates with masked or dct, not {method}")
            camera = parse_intrinsics(opt.intrinsics)
            height = integrate_perspective(normals, camera, mask=mask, method=method, distance=opt.distance)
            unit = "mm" if opt.distance else "relative depth"
        else:
            height = integrate(normals, method, mask=mask, pixel_size=opt.pixel_size or 1.0)
            unit = "mm" if opt.pixel_size else "pixel"
        if opt.flatten is not None:
            extra = {"cutoff_px": opt.flatten_cutoff} if opt.flatten == "highpass" else {}
            height = flatten(height, opt.flatten, mask=mask, **extra)
    step = opt.step or auto_step((h, w))
    decimation = None
    with stage("mesh"):
        mesh = grid_mesh(height, texture=texture, step=step, pixel_size=opt.pixel_size, normals=normals)
        if opt.decimate is not None or opt.max_error is not None:
            mesh, decimation = decimate(mesh, target_faces=opt.decimate, max_error=opt.max_error)
    with stage("write"):
        write_png(staging / "albedo.png", texture)
        jobs: dict[str, Callable[[], None]] = {
            # Longest first: OBJ text formatting holds the GIL, while PNG encoding and file
            # writes release it and proceed alongside.
            "mesh.obj": lambda: write_obj(staging / "mesh.obj", mesh, staging / "albedo.png"),
            "normals.png": lambda: write_png(staging / "normals.png", outputs.normals_to_rgb16(normals)),
            "mesh.ply": lambda: write_ply(staging / "mesh.ply", mesh, texture_file="mesh_texture.png"),
            "normals.npy": lambda: outputs.write_npy(staging / "normals.npy", normals),
            "height.tif": lambda: outputs.write_height_tiff(staging / "height.tif", height, unit, opt.pixel_size),
        }
        if mask is not None:
            jobs["mask.png"] = lambda: write_png(staging / "mask.png", mask.astype(np.uint8) * 255)
        if opt.glb:
            jobs["mesh.glb"] = lambda: write_glb(staging / "mesh.glb", mesh, texture)
        if opt.solid is not None:
            jobs["solid.stl"] = lambda: write_stl(staging / "solid.stl", solid(mesh, opt.solid))
        with ThreadPoolExecutor(max_workers=opt.threads or os.cpu_count() or 1) as pool:
            for future in [pool.submit(job) for job in jobs.values()]:
                future.result()
    facts = {"vertices": len(mesh.vertices), "faces": len(mesh.faces), "unit": unit, "step": step,
             "integrator": method, "integrator_reason": why,
             "decimation": json_safe(decimation)}
    return height, facts, ["albedo.png", *jobs, "mesh.mtl", "mesh_texture.png"]


def _report(inputs: dict, opt: RunOptions, mesh: dict, stage: _Stages, warnings: list[str], **extra) -> dict:
    return {
        "inputs": inputs,
        "parameters": {**{k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(opt).items()}, "step": mesh["step"]},
        "height_unit": mesh["unit"],
        **extra,
        "mesh": mesh,
        "stages": stage.timer.stages,
        "peak_rss_scope": "per stage" if stage.timer.per_stage_peak else "process since start",
        "versions": _versions(),
        "warnings": warnings,
    }


def _estimate_normals(
    stack, directions, opt: RunOptions, advance, near: NearLights | None = None
) -> tuple[np.ndarray, np.ndarray, int]:
    """Normals, luminance albedo and the count of undetermined pixels, by ``opt.normals``/``opt.fit``.

    Every fit here works on linear light, where a Lambertian surface's shading is n·l; the
    PTM written for viewers is fitted separately, to the photographs as encoded. With near
    lights every pixel has its own light directions: photometric stereo (with the plain fit's
    exclusion of shadowed and clipped samples) or the per-pixel PTM fit's maximum.
    """
    if near is not None:
        if opt.normals == "ptm-debiased":
            raise InputError("--normals ptm-debiased assumes distant lights; with near lights "
                             "use ps or ptm (or --light-positions none)")
        if opt.normals == "ptm":
            coefficients = fit_ptm_near(stack, near.positions, threads=opt.threads, progress=advance).coefficients
            normals = normals_from_ptm(coefficients)
            return normals, near_lambertian_albedo(stack, near.positions, normals, threads=opt.threads), 0
        ps = near_photometric_stereo(stack, near.positions, threads=opt.threads, progress=advance)
        return ps.normals, ps.albedo, int((~ps.valid).sum())
    if opt.normals == "ps":
        if opt.fit == "plain":
            ps = photometric_stereo(stack, directions, threads=opt.threads, progress=advance)
        else:
            ps = robust_photometric_stereo(stack, directions, method=opt.fit, threads=opt.threads, progress=advance)
        return ps.normals, ps.albedo, int((~ps.valid).sum())
    if opt.fit == "plain":
        coefficients = fit_ptm(stack, directions, solver=opt.solver, threads=opt.threads, progress=advance).coefficients
        if opt.normals == "ptm":
            normals = normals_from_ptm(coefficients)
        else:
            normals = debiased_normals(coefficients, hemisphere_coefficients(directions))
    else:
        fitted = robust_ptm(stack, directions, method=opt.fit, threads=opt.threads, progress=advance)
        normals = normals_from_ptm(fitted.ptm.coefficients) if opt.normals == "ptm" else fitted.normals
    return normals, lambertian_albedo(stack, directions, normals, threads=opt.threads), 0


def _leave_one_out(stack, directions, mask, staging: Path, threads, advance) -> dict:
    """Leave-one-out relighting error of PTM and HSH bases: maps written, RMS returned.

    Errors are in 8-bit sRGB levels, which is how the differences would look on screen.
    """
    import tifffile

    from ptmcore.images import linear_to_srgb
    from ptmcore.loo import loo_hsh, loo_ptm

    def levels(v: np.ndarray) -> np.ndarray:
        return 255.0 * linear_to_srgb(v)

    bases = {"ptm": lambda **kw: loo_ptm(stack, directions, **kw)}
    for order in (2, 3):
        bases[f"hsh{order}"] = lambda order=order, **kw: loo_hsh(stack, directions, order, **kw)
    result = {}
    for name, compute in bases.items():
        rms_map, rms = compute(mask=mask, transform=levels, threads=threads, progress=advance)
        with atomic_write(staging / f"loo_{name}.tif", "wb") as f:
            tifffile.imwrite(f, rms_map.astype(np.float32), metadata={"unit": "8-bit sRGB levels"})
        result[name] = float(rms)
    return {"rms_levels": result, "best": min(result, key=result.get), "unit": "8-bit sRGB levels"}


def _light_model(near: NearLights | None, shape: tuple[int, int], opt: RunOptions) -> dict:
    """What report.json says of the light model: distant directions or near point lights."""
    if near is None:
        return {"type": "distant", "detail": "one light direction per photograph"}
    return json_safe({
        "type": "near",
        "source": near.source,
        "median_distance_px": typical_distance(near.positions, shape),
        "detail": "each pixel has its own light direction and inverse-square falloff "
                  f"({'PTM maximum of a per-pixel fit' if opt.normals == 'ptm' else 'photometric stereo, plain fit'}); "
                  "coefficients.ptm and the other relighting files use the direction from the image centre",
    })


def _rank_summary(rank) -> dict:
    """What report.json says of the light layout: rank and condition of the PTM light matrix."""
    return json_safe({
        "rank": rank.rank,
        "condition": rank.condition if math.isfinite(rank.condition) else None,
        "singular_values": rank.singular_values,
        "tolerance": rank.tolerance,
        "causes": rank.causes,
    })


def _ptm_summary(quantisation: dict, bit_depth: int) -> dict:
    """What report.json says of coefficients.ptm: format, size, encoding and its 8-bit quantisation error.

    The PTM is fitted to the photographs as they are encoded: sRGB for 8-bit photographs,
    linear light (scaled to 0-255) for 16-bit ones, which viewers then show dark; the preview
    and report.html encode a linear PTM's renderings as sRGB for display.
    """
    keep = ("format", "width", "height", "scale", "bias", "bytes", "max_error", "rms_error", "clipped")
    summary = {k: quantisation[k] for k in keep if k in quantisation}
    summary["encoding"] = "sRGB" if bit_depth <= 8 else "linear"
    if "hsh" in quantisation:
        summary["hsh_rti"] = {k: v for k, v in quantisation["hsh"].items() if k != "path"}
    summary["error_unit"] = "coefficient units (luminance 0-255)"
    return json_safe(summary)


def json_safe(value):
    """Convert NumPy scalars and arrays inside ``value`` to plain Python for JSON."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None  # JSON has no NaN or infinity
    return value


def _write_reports(staging: Path, report: dict, stage: _Stages, page: bool = True, **html) -> list[str]:
    """Write report.html (unless ``page`` is False) from the staging folder and the report,
    then report.json with the page's own time; return their names."""
    if not page:
        outputs.write_json(staging / "report.json", report)
        return ["report.json"]
    with stage("report"):
        write_report_html(staging, report=report, **html)
    outputs.write_json(staging / "report.json", report)
    return ["report.json", "report.html"]


def _publish(staging: Path, out: Path, names: list[str]) -> dict[str, Path]:
    """Move the finished files from the staging folder into the output folder."""
    final = {}
    for name in names:
        (out / name).parent.mkdir(exist_ok=True)
        os.replace(staging / name, out / name)
        final[name] = out / name
    return final


def run(
    source: str | os.PathLike,
    output: str | os.PathLike,
    options: RunOptions | None = None,
    *,
    progress: ProgressFn | None = None,
    report_page: bool = True,
) -> RunResult:
    """Reconstruct a capture folder, an ``.lp`` file or an existing ``.ptm`` file.

    See :func:`run_capture` and :func:`run_ptm`. ``report_page=False`` leaves report.html
    to a step that follows (``run --scan``: :func:`run_compare` writes it with the comparison).
    """
    if Path(source).suffix.lower() == ".ptm" and Path(source).is_file():
        return run_ptm(source, output, options, progress=progress, report_page=report_page)
    return run_capture(source, output, options, progress=progress, report_page=report_page)


def run_capture(
    capture: str | os.PathLike,
    output: str | os.PathLike,
    options: RunOptions | None = None,
    *,
    progress: ProgressFn | None = None,
    report_page: bool = True,
) -> RunResult:
    """Reconstruct one capture and write the output folder.

    Parameters
    ----------
    capture : path
        A capture folder (photographs and one ``.lp`` file) or an ``.lp`` file.
    output : path
        Output folder; created if needed. Files are written to a staging folder inside it and
        moved into place only when every stage succeeded, so a failed run leaves earlier
        results untouched and nothing half-written.
    options : RunOptions, optional
    progress : callable, optional
        ``progress(stage, done, total)`` as work advances.
    report_page : bool
        Write report.html (False when a step that follows writes it, as ``run --scan`` does).

    Returns
    -------
    RunResult

    Raises
    ------
    InputError
        For any problem with the inputs or the output folder.
    """
    opt = options or RunOptions()
    _check_options(opt)
    capture = Path(capture)
    out = Path(output)
    dataset = opt.lp is None and capture.is_dir() and is_ps_dataset(capture)
    calibrate_spheres = (
        opt.lp is None and not dataset and capture.is_dir()
        and not any(p.suffix.lower() == ".lp" for p in capture.iterdir())
    )
    sphere_mask = None
    near = None
    if dataset:
        lp_path = None
        lights = None
        if str(opt.light_positions) not in ("auto", "none"):
            raise InputError("light positions apply to captures with an .lp file or spheres, "
                             "not to a photometric-stereo dataset", capture)
    elif calibrate_spheres:
        lp_path = None
        try:
            photographs = capture_images(capture)
        except InputError as exc:
            raise InputError(f"no .lp light file, and {exc.problem}", capture) from None
    else:
        lp_path = find_lp(capture, opt.lp)
        lights = read_lp(lp_path)
        near = _near_lights_from_file(lights, lp_path, opt.light_positions)
    gt_dir = opt.ground_truth
    if gt_dir is None:
        guess = (capture if capture.is_dir() else capture.parent) / "ground_truth"
        gt_dir = guess if (guess / "normals.npy").exists() else None

    stage = _Stages(progress)
    staging = _prepare_output(out)
    warnings: list[str] = []
    try:
        truth = None
        if dataset:
            with stage("decode"):
                ds = read_ps_dataset(capture, threads=opt.threads)
            stack, lights = ds.stack, ds.lights
            if ds.ground_truth_normals is not None and gt_dir is None:
                gt_mask = ds.mask if ds.mask is not None else np.ones(stack.shape, bool)
                truth = GroundTruth(ds.ground_truth_normals, gt_mask)
        elif calibrate_spheres:
            with stage("decode", len(photographs)) as advance:
                stack = load_stack(photographs, linearize=opt.linearize, threads=opt.threads, progress=advance)
            stack, lights, sphere_mask, near = _calibrate_from_spheres(stack, capture, warnings, opt)
        else:
            with stage("decode", len(lights)) as advance:
                stack = load_stack(lights.paths, linearize=opt.linearize, threads=opt.threads, progress=advance)
        h, w = stack.shape
        bit_depth = stack.bit_depth
        if opt.mask is not None and str(opt.mask) != "auto":
            mask = read_mask(opt.mask, (h, w))
        else:
            mask = ds.mask if dataset else None
        if sphere_mask is not None:
            mask = sphere_mask if mask is None else (mask & sphere_mask)
        intensity = None
        if opt.intensities is not None:
            if opt.intensities == "estimate":
                factors = estimate_intensities(stack, lights.directions, mask=mask)
            else:
                factors = read_intensities(opt.intensities, len(lights))
            stack = apply_intensities(stack, factors)
            intensity = {"source": opt.intensities, "factors": factors}
        rank = analyse_lights(lights.directions)
        if rank.deficient:
            warnings.append(f"the PTM light matrix has rank {rank.rank} of 6: " + "; ".join(rank.causes))
        saturated = stack.saturated / (h * w)
        if saturated.max() > 0.01:
            worst = int(np.argmax(saturated))
            warnings.append(
                f"{np.count_nonzero(saturated > 0.01)} photograph(s) have more than 1% clipped pixels "
                f"(most: {stack.paths[worst].name}, {saturated[worst]:.1%}); clipped samples are left "
                "out of photometric stereo"
            )

        with stage("normals", h) as advance:
            normals, albedo, undetermined = _estimate_normals(stack, lights.directions, opt, advance, near)
        if undetermined:
            warnings.append(
                f"{undetermined} pixels ({undetermined / (h * w):.2%}) had too few lit, unsaturated "
                "photographs to determine a normal; their normal is set to (0, 0, 1)"
            )
        albedo_rgb = stack.chroma * albedo[..., None]
        if str(opt.mask) == "auto":
            mask = _auto_mask(albedo_rgb, normals, warnings)
        texture, albedo_scale = outputs.albedo_to_srgb8(albedo_rgb)
        del albedo_rgb
        loo = None
        if opt.loo:
            with stage("loo", 3 * h) as advance:
                loo = _leave_one_out(stack, lights.directions, mask, staging, opt.threads, advance)
        # The stack is by far the largest array; no later stage needs it.
        del stack

        with stage("ptm", len(lights)) as advance:
            # A second pass over the photographs, as they are encoded: the fit HP's PTMfitter
            # makes (its files are reproduced byte for byte), streamed so memory stays bounded.
            if opt.ptm_format == "lrgb":
                coef8, rgb8 = fit_ptm_encoded(
                    lights.paths, lights.directions, solver=opt.solver, threads=opt.threads, progress=advance
                )
            else:
                coef8 = fit_ptm_rgb_encoded(
                    lights.paths, lights.directions, solver=opt.solver, threads=opt.threads, progress=advance
                )
                rgb8 = None
            quantisation = write_ptm(staging / "coefficients.ptm", coef8, rgb8)
            ptm_names = ["coefficients.ptm"]
            if rgb8 is not None:
                ptm_names += _web_export(staging, coef8, rgb8, opt.pixel_size)
            else:
                warnings.append("no web/ export: the OpenLIME export takes an LRGB PTM (use --ptm-format lrgb)")
            del coef8, rgb8
            if opt.hsh:
                hsh = fit_rti_hsh(lights.paths, lights.directions, order=3, threads=opt.threads)
                quantisation["hsh"] = write_rti_hsh(staging / "coefficients.rti", hsh, order=3)
                ptm_names.append("coefficients.rti")
                del hsh

        height, mesh, names = _surface_and_files(normals, texture, mask, opt, staging, stage)

        accuracy = None
        if gt_dir is not None:
            truth = load_ground_truth(gt_dir)
        if truth is not None:
            accuracy = {"ground_truth": str(gt_dir or capture), "normals": normal_accuracy(normals, truth)}
            rmse = height_rmse(height, truth) if opt.pixel_size else None
            if rmse is not None:
                accuracy["height_rmse_mm"] = rmse

        inputs = {
            "capture": str(capture.resolve()),
            "lp": str(lp_path.resolve()) if lp_path else None,
            "layout": "photometric-stereo dataset" if dataset else (
                "capture with spheres (calibrated)" if calibrate_spheres else "capture with .lp"),
            "photographs": len(lights),
            "width": w,
            "height": h,
            "bit_depth": bit_depth,
            "mask": _mask_source(opt.mask, mask),
        }
        report = _report(
            inputs, opt, mesh, stage, warnings, albedo_scale=albedo_scale,
            lights=_rank_summary(rank), light_model=_light_model(near, (h, w), opt),
            intensities=json_safe(intensity), ptm=_ptm_summary(quantisation, bit_depth),
            leave_one_out=loo, accuracy=accuracy,
        )
        if near is not None:
            write_light_positions(staging / "light_positions.csv", [p.name for p in lights.paths], near.positions)
            names.append("light_positions.csv")
        reports = _write_reports(staging, report, stage, report_page,
                                 photographs=list(zip(lights.paths, lights.directions)))
        loo_names = [f"loo_{b}.tif" for b in (loo or {}).get("rms_levels", {})]
        final = _publish(staging, out, [*ptm_names, *loo_names, *names, *reports])
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return RunResult(out, final, report)


def _evaluate(coefficients: np.ndarray, lu: np.ndarray, lv: np.ndarray) -> np.ndarray:
    """Each pixel's polynomial ``(..., 6)`` at its own light ``(lu, lv)``."""
    basis = np.stack([lu * lu, lv * lv, lu * lv, lu, lv, np.ones_like(lu)], axis=-1)
    if coefficients.ndim == basis.ndim + 1:  # RGB format: (H, W, 3, 6)
        basis = basis[..., None, :]
    return (coefficients * basis).sum(axis=-1)


def run_ptm(
    ptm_path: str | os.PathLike,
    output: str | os.PathLike,
    options: RunOptions | None = None,
    *,
    progress: ProgressFn | None = None,
    report_page: bool = True,
) -> RunResult:
    """Normals, height and meshes from an existing ``.ptm`` file (no photographs needed).

    The normals are the PTM's maxima (photometric stereo needs the photographs); the texture
    is the PTM's colour under the light of its maximum, i.e. its albedo in the file's own
    encoding. Parameters and output folder as :func:`run_capture`.
    """
    from dataclasses import replace

    opt = replace(options or RunOptions(), normals="ptm")
    _check_options(opt)
    ptm_path = Path(ptm_path)
    out = Path(output)
    stage = _Stages(progress)
    staging = _prepare_output(out)
    warnings = ["normals come from the PTM's maximum: a .ptm file carries no photographs for photometric stereo"]
    try:
        with stage("decode"):
            ptm = read_ptm(ptm_path)
        h, w = ptm.coefficients.shape[:2]
        mask = read_mask(opt.mask, (h, w)) if opt.mask is not None and str(opt.mask) != "auto" else None
        with stage("normals", h):
            coef = ptm.coefficients
            # RGB format: one polynomial per channel, and luminance is linear in them.
            luminance = coef if coef.ndim == 3 else np.einsum("hwck,c->hwk", coef, LUMA_WEIGHTS)
            normals = normals_from_ptm(luminance)
            lu, lv = normals[..., 0], normals[..., 1]
            if ptm.rgb is not None:
                top = _evaluate(luminance, lu, lv)[..., None] * ptm.rgb / np.float32(255)
            else:
                top = _evaluate(coef, lu, lv)
            texture = np.clip(np.round(top), 0, 255).astype(np.uint8)
        if str(opt.mask) == "auto":
            mask = _auto_mask(texture.astype(np.float32) / 255, normals, warnings)
        web = _web_export(staging, ptm.coefficients, ptm.rgb, opt.pixel_size) if ptm.rgb is not None else []
        height, mesh, names = _surface_and_files(normals, texture, mask, opt, staging, stage)
        inputs = {"ptm": str(ptm_path.resolve()), "format": ptm.format, "width": w, "height": h,
                  "mask": _mask_source(opt.mask, mask)}
        report = _report(inputs, opt, mesh, stage, warnings, accuracy=None)
        # The page relights a subsample of the source .ptm: read again, only that is decoded.
        reports = _write_reports(staging, report, stage, report_page)
        final = _publish(staging, out, [*web, *names, *reports])
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return RunResult(out, final, report)


def run_normals(
    normal_map: str | os.PathLike,
    output: str | os.PathLike,
    options: RunOptions | None = None,
    *,
    progress: ProgressFn | None = None,
) -> RunResult:
    """Height map and meshes from a normal map made elsewhere (``reconstruct integrate``).

    The map is read by :func:`reconstruct.surface.normalmaps.read_normal_map`; pixels without a valid
    normal are outside the object unless a mask says otherwise. The texture is a grey shaded
    rendering of the normals. Parameters and output folder as :func:`run_capture`.
    """
    opt = options or RunOptions()
    _check_options(opt)
    path = Path(normal_map)
    out = Path(output)
    stage = _Stages(progress)
    staging = _prepare_output(out)
    warnings: list[str] = []
    try:
        with stage("decode"):
            normals = read_normal_map(path)
        h, w = normals.shape[:2]
        valid = np.isfinite(normals[..., 0])
        if str(opt.mask) == "auto":
            mask = _auto_mask(shaded(normals).astype(np.float32) / 255, np.nan_to_num(normals), warnings)
        elif opt.mask is not None:
            mask = read_mask(opt.mask, (h, w))
            if (mask & ~valid).any():
                warnings.append(f"{int((mask & ~valid).sum())} pixels inside the mask have no valid normal")
        else:
            mask = None if valid.all() else valid
        height, mesh, names = _surface_and_files(normals, shaded(normals), mask, opt, staging, stage)
        inputs = {"normal_map": str(path.resolve()), "width": w, "height": h,
                  "mask": _mask_source(opt.mask, mask) if opt.mask else ("valid normals" if mask is not None else None)}
        report = _report(inputs, opt, mesh, stage, warnings, accuracy=None)
        reports = _write_reports(staging, report, stage)
        final = _publish(staging, out, [*names, *reports])
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return RunResult(out, final, report)


@dataclass
class CompareOptions:
    """Parameters of :func:`run_compare` (``reconstruct compare``).

    Attributes
    ----------
    scan_units : {"mm", "cm", "m", "in"}
        Unit of the scan's coordinates.
    scale : bool
        Also estimate a global scale (photometric heights can carry a scale error).
    initial : Path or None
        A 4×4 matrix (text) taking the scan near the reconstruction, to start from.
    no_align : bool
        The two are already aligned.
    tolerance : float or None
        Acceptance tolerance in mm: the share of scan points within it is reported, and
        :attr:`CompareResult.passed` says whether it reaches ``min_fraction``.
    min_fraction : float
        Share of points within tolerance needed to pass.
    reverse : bool
        Also measure the reconstruction's distances to the scan.
    max_distance : float or None
        Points farther than this (mm) from the reconstruction are outside the overlap
        (default: from the alignment's residual).
    """

    scan_units: str = "mm"
    scale: bool = False
    initial: Path | None = None
    no_align: bool = False
    tolerance: float | None = None
    min_fraction: float = 0.95
    reverse: bool = False
    max_distance: float | None = None


@dataclass
class CompareResult:
    """What :func:`run_compare` produced."""

    output: Path
    files: dict[str, Path]
    report: dict
    passed: bool | None = None


def _read_initial(path: Path) -> np.ndarray:
    try:
        m = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the initial transform ({exc})", path) from None
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise InputError(f"the initial transform must be a 4×4 matrix of numbers, got shape {m.shape}", path)
    return m


def run_compare(
    reconstruction: str | os.PathLike,
    scan: str | os.PathLike,
    output: str | os.PathLike,
    options: CompareOptions | None = None,
) -> CompareResult:
    """Align a scan to a reconstruction, measure their distances and write the comparison.

    ``reconstruction`` is a mesh or an output folder of ``reconstruct run`` (its mesh.ply,
    which must be in millimetres). Writes ``comparison.json``, ``distances.ply`` (the
    reconstruction coloured by its distance to the scan, or the scan points when the
    reconstruction is a point cloud), ``histogram.png``, ``overlay.png`` (an off-screen
    render; skipped with a warning where the machine cannot render) and ``report.html``
    (with the reconstruction's own report when it is an output folder).
    """
    from reconstruct.compare.align import align, distances, load_geometry, within_tolerance
    from reconstruct.compare.figures import (
        default_limit,
        write_distance_ply,
        write_histogram,
        write_overlay,
    )

    opt = options or CompareOptions()
    if opt.tolerance is not None and not (math.isfinite(opt.tolerance) and opt.tolerance > 0):
        raise InputError(f"the tolerance must be a positive number of millimetres, got {opt.tolerance}")
    if not 0 < opt.min_fraction <= 1:
        raise InputError(f"the fraction needed within tolerance must be in (0, 1], got {opt.min_fraction}")
    rec_path = Path(reconstruction)
    rec_folder = rec_path if rec_path.is_dir() else None
    warnings: list[str] = []
    if rec_path.is_dir():
        report_file = rec_path / "report.json"
        if report_file.exists():
            import json

            unit = json.loads(report_file.read_text()).get("height_unit")
            if unit != "mm":
                raise InputError(f"this reconstruction's heights are in {unit}, not mm: run it with --pixel-size", rec_path)
        rec_path = rec_path / "mesh.ply"
    rec = load_geometry(rec_path)
    scan_geometry = load_geometry(scan, units=opt.scan_units)
    initial = _read_initial(opt.initial) if opt.initial is not None else None
    out = Path(output)
    staging = _prepare_output(out)
    timer = StageTimer()
    try:
        with timer.stage("align"):
            alignment = align(rec, scan_geometry, scale=opt.scale, initial=initial, no_align=opt.no_align)
        with timer.stage("distances"):
            result = distances(rec, scan_geometry, alignment, reverse=opt.reverse or rec.faces is not None,
                               max_distance=opt.max_distance)
        d = result.signed[result.mask]
        limit = default_limit(d)
        names = ["comparison.json", "distances.ply", "histogram.png"]
        with timer.stage("write"):
            if rec.faces is not None and result.reverse is not None:
                # The reconstruction's distance to the scan, with the scan's sign convention
                # (positive: the scan lies on the camera side).
                on_rec = np.where(result.reverse_mask, -result.reverse, np.nan)
                write_distance_ply(staging / "distances.ply", rec.points, rec.faces, on_rec, limit)
            else:
                on_rec = None
                write_distance_ply(staging / "distances.ply", result.aligned_points, None,
                                   np.where(result.mask, result.signed, np.nan), limit)
            fraction = within_tolerance(result, opt.tolerance) if opt.tolerance is not None else None
            write_histogram(staging / "histogram.png", d, result.stats, tolerance=opt.tolerance)
            try:
                if rec.faces is not None:
                    shown = on_rec if on_rec is not None else np.where(result.mask, result.signed, np.nan)
                    write_overlay(staging / "overlay.png", rec.points, rec.faces, result.aligned_points, shown, limit)
                    names.append("overlay.png")
                else:
                    warnings.append("no overlay.png: the reconstruction is a point cloud")
            except RuntimeError as exc:
                warnings.append(f"no overlay.png: {exc}")
        passed = None if fraction is None else bool(fraction >= opt.min_fraction)
        report = json_safe({
            "reconstruction": str(rec_path.resolve()),
            "scan": str(Path(scan).resolve()),
            "units": {"distances": "mm", "scan_input": opt.scan_units},
            "parameters": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(opt).items()},
            "alignment": {
                "transform_scan_to_reconstruction": alignment.transform,
                "scale": alignment.scale,
                "fitness": alignment.fitness,
                "inlier_rmse_mm": alignment.inlier_rmse,
                "method": alignment.method,
            },
            "statistics_mm": result.stats,
            "reverse_statistics_mm": result.reverse_stats,
            "tolerance": None if fraction is None else {
                "tolerance_mm": opt.tolerance, "fraction_within": fraction,
                "min_fraction": opt.min_fraction, "passed": passed,
            },
            "colour_range_mm": [-limit, limit],
            "sign_convention": "positive: the scan lies on the camera side of the reconstruction",
            "stages": timer.stages,
            "versions": _versions(),
            "warnings": warnings,
        })
        # The page also shows the reconstruction's report when the comparison is written
        # beside it (``run --scan``) or made from its output folder; comparison.json follows
        # it, with its time.
        with timer.stage("report"):
            write_report_html(staging, comparison=report, also=[out, *([rec_folder] if rec_folder else [])])
        report["stages"] = json_safe(timer.stages)
        outputs.write_json(staging / "comparison.json", report)
        final = _publish(staging, out, [*names, "report.html"])
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return CompareResult(out, final, report, passed)
