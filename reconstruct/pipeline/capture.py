"""Loading a capture: its photographs, lights, mask, near lights and ground truth, checked.

:func:`load_capture` is the first stage of a run. It accepts the three layouts a user may
hand over and returns one :class:`Capture` whatever the layout:

* a folder of photographs with one ``.lp`` light file (or the ``.lp`` file itself);
* a photometric-stereo dataset folder (DiLiGenT's ``filenames.txt``, ``light_directions.txt``
  and ``light_intensities.txt``, :mod:`ptmcore.psdataset`);
* a folder of photographs with glossy spheres in view and no ``.lp``: the lights are read from
  the spheres' highlights (:mod:`reconstruct.calibration`), near lights triangulated when two
  or more spheres show them.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ptmcore.corrections import Corrections
from ptmcore.errors import InputError, first_few
from ptmcore.images import ImageStack, check_content, image_size, load_stack, load_stack_and_fits, read_image
from ptmcore.intensity import apply_intensities, estimate_intensities, read_intensities
from ptmcore.lp import LightSet, read_lp
from ptmcore.nearlight import read_light_positions
from ptmcore.ptmencoded import EncodedFit, EncodedFits
from ptmcore.psdataset import is_ps_dataset, read_ps_dataset
from ptmcore.raw import RAW_SUFFIXES
from ptmcore.resources import RUN_BASE_MB, RUN_BYTES_PER_PIXEL, available_memory_mb
from ptmcore.solvers import RankInfo, analyse_lights
from reconstruct.pipeline.defects import (
    CLIPPED_SHARE,
    capture_corrections,
    drift_finding,
    exposure_finding,
    new_probe,
    sampled_luminance,
    stray_light_finding,
)
from reconstruct.pipeline.options import STACK_FILE_MB, RunOptions
from reconstruct.pipeline.profiling import Stages
from reconstruct.pipeline.projects import locate_photographs, project_lp
from reconstruct.surface.accuracy import GroundTruth, load_ground_truth

__all__ = [
    "IMAGE_SUFFIXES",
    "Capture",
    "NearLights",
    "capture_images",
    "find_lp",
    "load_capture",
    "read_mask",
]

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", *sorted(RAW_SUFFIXES))

#: How report.json names each layout.
LP_CAPTURE = "capture with .lp"
PS_DATASET = "photometric-stereo dataset"
SPHERE_CAPTURE = "capture with spheres (calibrated)"


@dataclass
class NearLights:
    """Point lights of a capture: positions ``(N, 3)`` float64 in pixels (x = column,
    y = −row, z above the base plane) and where they came from."""

    positions: np.ndarray
    source: str


@dataclass
class Capture:
    """A loaded capture, ready for the normals and relighting stages.

    Attributes
    ----------
    source : Path
        The capture folder or ``.lp`` file as given.
    layout : str
        ``"capture with .lp"``, ``"photometric-stereo dataset"`` or
        ``"capture with spheres (calibrated)"``.
    stack : ImageStack
        The photographs as linear luminance ``(N, H, W)`` uint16 with clip marks and per-pixel
        chromaticity ``(H, W, 3)`` (:func:`ptmcore.images.load_stack`), divided by the light
        intensities when they were given or estimated.
    lights : LightSet
        Each photograph's path and unit light direction ``(N, 3)`` (x right, y up, z towards
        the camera); for near lights, the direction from the image centre.
    lp_path : Path or None
        The ``.lp`` file read, if any.
    mask : ndarray or None
        ``(H, W)`` bool, True on the object: from ``--mask FILE``, the dataset's own mask, and
        the spheres left out. ``--mask auto`` is resolved later, from the normals.
    near : NearLights or None
        Light positions when the lights are near (each pixel then has its own directions).
    truth : GroundTruth or None
        Ground-truth normals (and heights) to measure accuracy against.
    truth_source : str or None
        Where the ground truth came from.
    rank : RankInfo
        Rank and conditioning of the PTM light matrix.
    intensities : dict or None
        ``{"source": …, "factors": (N,) or (N, 3)}`` when intensities were applied.
    warnings : list of str
        What a user should know about the capture (clipping, left-out photographs, ...).
    fits : EncodedFits or None
        The PTM (and HSH) fitted to the photographs as encoded, made in the decoding pass when
        the photographs and their lights were known before it (a capture with an ``.lp``);
        :func:`reconstruct.pipeline.fit_relighting` uses them, and fits from the files
        otherwise (or if photographs or lights changed since).
    corrections : Corrections or None
        What was done to each photograph after decoding (the ambient frame subtracted, the
        camera's drift undone): a later pass over the files does the same
        (:mod:`reconstruct.pipeline.defects`).
    checks : dict
        What was found about the capture (colour profile, drift, ambient frame, stray light):
        ``report.json``'s ``capture_checks``.
    """

    source: Path
    layout: str
    stack: ImageStack
    lights: LightSet
    lp_path: Path | None = None
    mask: np.ndarray | None = None
    near: NearLights | None = None
    truth: GroundTruth | None = None
    truth_source: str | None = None
    rank: RankInfo | None = None
    intensities: dict | None = None
    warnings: list[str] = field(default_factory=list)
    fits: EncodedFits | None = None
    corrections: Corrections | None = None
    checks: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the photographs."""
        return self.stack.shape


def find_lp(capture: Path, lp: Path | None = None) -> Path:
    """The light file of a capture: ``lp`` if given, the capture itself if it is an ``.lp``
    file, else the single ``.lp`` file in the capture folder, or in its ``assembly-files/``
    for an RTIBuilder project (:func:`reconstruct.pipeline.projects.project_lp`).

    Anything named ``*.lp`` counts, a broken link or a folder too: reading it then says what
    is wrong with it, where skipping it would say there is no light file, or take another.
    """
    if lp is not None:
        return Path(lp)
    capture = Path(capture)
    if capture.suffix.lower() == ".lp" and not capture.is_dir():
        return capture
    if capture.is_file():
        raise InputError("not a capture folder or .lp file", capture)
    if not capture.is_dir():
        raise InputError("capture folder not found", capture)
    found = sorted(p for p in capture.iterdir() if p.suffix.lower() == ".lp")
    if not found:
        project = project_lp(capture)
        if project is not None:
            return project
        raise InputError("no .lp light file in the capture folder (give one with --lp)", capture)
    if len(found) > 1:
        names = ", ".join(p.name for p in found)
        raise InputError(f"several .lp files ({names}); choose one with --lp", capture)
    return found[0]


def capture_images(folder: str | os.PathLike) -> list[Path]:
    """The photographs of a capture folder, in name order."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("capture folder not found", folder)
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not paths:
        raise InputError("no photographs (JPEG, PNG, TIFF or camera RAW) in the capture folder", folder)
    return paths


def read_mask(path: Path, shape: tuple[int, int], against: str = "the photographs") -> np.ndarray:
    """Read a ``--mask`` image (non-zero = object) and check it matches what it masks.

    Parameters
    ----------
    path : Path
        The mask image (grey or colour; a pixel is the object where any channel is non-zero).
    shape : tuple of int
        ``(H, W)`` it must have.
    against : str
        What gives that size, for the message ("the photographs", "the normal map", ...).

    Returns
    -------
    ndarray, shape (H, W), bool

    Raises
    ------
    InputError
        If the image cannot be read, is of another size, or has no non-zero pixel.
    """
    m = read_image(path)
    if m.ndim == 3:
        m = m.max(axis=2)
    if m.shape != tuple(shape):
        raise InputError(f"the --mask image is {m.shape[1]}×{m.shape[0]} pixels; it must match the size of "
                         f"{against}, {shape[1]}×{shape[0]}", path)
    m = m > 0
    if not m.any():
        raise InputError("the --mask image is empty (no non-zero pixel)", path)
    return m


def _layout(capture: Path, opt: RunOptions) -> str:
    """Which of the three layouts ``capture`` is."""
    if opt.lp is None and capture.is_dir():
        if is_ps_dataset(capture):
            return PS_DATASET
        if not any(p.suffix.lower() == ".lp" for p in capture.iterdir()) and project_lp(capture) is None:
            return SPHERE_CAPTURE
    return LP_CAPTURE


def _near_lights_from_file(lights: LightSet, lp_path: Path, option: Path | str) -> NearLights | None:
    """Positions for the photographs of ``lights`` from a light-position file, if there is one.

    With ``"auto"`` the file is ``light_positions.csv`` beside the ``.lp``; photographs are
    matched by file name, and every photograph of the ``.lp`` needs a position.
    """
    if option == "none":
        return None
    path = lp_path.parent / "light_positions.csv" if option == "auto" else Path(option)
    if option == "auto" and not os.path.lexists(path):
        return None
    names, positions = read_light_positions(path)
    by_name = dict(zip(names, positions))
    missing = [p.name for p in lights.paths if p.name not in by_name]
    if missing:
        raise InputError(f"no light position for {first_few(missing)}", path)
    return NearLights(np.array([by_name[p.name] for p in lights.paths]), str(path))


def _sphere_mask(spheres, shape: tuple[int, int]) -> np.ndarray:
    """True away from the spheres (and their dark rims, a few pixels wider)."""
    rows, cols = np.ogrid[0 : shape[0], 0 : shape[1]]
    keep = np.ones(shape, bool)
    for cx, cy, r in spheres:
        keep &= (cols - cx) ** 2 + (rows - cy) ** 2 > (r + 3) ** 2
    return keep


def _calibrate_from_spheres(stack: ImageStack, capture: Path, opt: RunOptions) -> Capture:
    """Lights read from the glossy spheres of a decoded capture that has no .lp file.

    The photographs without a usable light are left out; the spheres are masked out of the
    reconstruction; with two or more spheres showing near lights, every triangulated
    photograph is kept, even where the spheres' distant directions disagree, as they must
    for a near light.
    """
    from reconstruct.calibration.calibrate import calibration_camera
    from reconstruct.calibration.triangulate import sphere_lights

    camera = calibration_camera(stack.paths[0], stack.shape, intrinsics=opt.intrinsics)
    try:
        found = sphere_lights(stack, intrinsics=camera, near=opt.light_positions == "auto")
    except InputError as exc:
        raise InputError(
            f"no .lp light file (give one with --lp), and no light directions from spheres either: {exc.problem}",
            capture,
        ) from None
    spheres = found.calibration.spheres
    warnings = [f"{line}; left out" for line in found.left_out]
    usable = found.usable
    if usable.sum() < 3:
        what = "a triangulated light position" if found.positions is not None else "a usable sphere highlight"
        raise InputError(f"fewer than 3 photographs have {what}", capture)
    stack = stack.select(usable)
    near = None
    counts = f"{int(usable.sum())} of {len(usable)} photographs"
    if found.positions is not None:
        near = NearLights(found.positions, f"triangulated from {len(spheres)} spheres")
        warnings.append(f"no .lp file: near lights triangulated from {len(spheres)} spheres for {counts}; "
                        "each pixel has its own light direction")
    else:
        warnings.append(f"no .lp file: light directions read from {len(spheres)} sphere(s) for {counts} "
                        f"({found.calibration.view_model} view)")
    return Capture(capture, SPHERE_CAPTURE, stack, LightSet(stack.paths, found.directions, None),
                   mask=_sphere_mask(spheres, stack.shape), near=near, warnings=warnings)


def _decode(capture: Path, layout: str, opt: RunOptions, stages: Stages, scratch: str | os.PathLike | None
            ) -> Capture:
    """The photographs and lights of ``capture``, decoded."""
    if layout == PS_DATASET:
        if opt.light_positions not in ("auto", "none"):
            raise InputError("light positions apply to captures with an .lp file or spheres, "
                             "not to a photometric-stereo dataset", capture)
        if opt.ambient is not None or opt.flat_field is not None:
            raise InputError("--ambient and --flat-field apply to captures with an .lp file, not to a "
                             "photometric-stereo dataset", capture)
        with stages("decode"):
            # Intensities asked for replace the dataset's own (estimated ones are estimated on
            # the photographs as stored).
            ds = read_ps_dataset(capture, threads=opt.threads, divide_intensities=opt.intensities is None)
        loaded = Capture(capture, layout, ds.stack, ds.lights, mask=ds.mask)
        loaded.warnings += ds.lights.warnings
        if ds.ground_truth_normals is not None:
            gt_mask = ds.mask if ds.mask is not None else np.ones(ds.stack.shape, bool)
            loaded.truth, loaded.truth_source = GroundTruth(ds.ground_truth_normals, gt_mask), str(capture)
        return loaded
    if layout == SPHERE_CAPTURE:
        try:
            photographs = capture_images(capture)
        except InputError as exc:
            raise InputError(f"no .lp light file, and {exc.problem}", capture) from None
        on_disk, warnings = _stack_place(photographs, opt, scratch)
        # The lights are read from the decoded photographs: the ambient frame is subtracted,
        # the drift (measured against the lights) is not.
        corrections, checks = capture_corrections(photographs, ambient=opt.ambient, flat_field=opt.flat_field)
        with stages("decode", len(photographs)) as advance:
            stack = load_stack(photographs, linearize=opt.linearize, threads=opt.threads, progress=advance,
                               storage=_storage(opt), on_disk=on_disk, corrections=corrections)
        loaded = _calibrate_from_spheres(stack, capture, opt)
        loaded.warnings[:0] = warnings
        loaded.corrections, loaded.checks = corrections, checks
        return loaded
    lp_path = find_lp(capture, opt.lp)
    lights = locate_photographs(read_lp(lp_path), capture)
    near = _near_lights_from_file(lights, lp_path, opt.light_positions)
    # The photographs and their lights are known before decoding, so the files viewers open
    # are fitted in the same pass (with near lights too: they use one direction per photograph).
    fit = EncodedFit(lights.directions, opt.ptm_format, opt.solver, 3 if opt.hsh else None, opt.ptm_encoding)
    on_disk, warnings = _stack_place(lights.paths, opt, scratch)
    corrections, checks = capture_corrections(lights.paths, ambient=opt.ambient, flat_field=opt.flat_field,
                                              directions=lights.directions)
    # Measured with --align off too (a fraction of a second): the drift is then said, not undone.
    probe = new_probe(lights.paths)
    kw = {"fit": fit, "linearize": opt.linearize, "threads": opt.threads, "storage": _storage(opt), "on_disk": on_disk,
          "corrections": corrections}
    with stages("decode", len(lights)) as advance:
        stack, fits = load_stack_and_fits(lights.paths, progress=advance, probe=probe, **kw)
    warnings = [*lights.warnings, *warnings]
    if probe is not None:
        from ptmcore.align import measure_drift

        drift = measure_drift(probe, lights.directions, threads=opt.threads)
        del probe
        checks["drift"], said, resample = drift_finding(drift, [p.name for p in lights.paths], opt.align)
        warnings += said
        if resample:
            # Decoded again, each photograph resampled onto the common frame: only a capture
            # that moved pays a second pass; a steady one paid the measurement alone.
            corrections.transforms = drift.resampling()
            del stack, fits
            with stages("align", len(lights)) as advance:
                stack, fits = load_stack_and_fits(lights.paths, progress=advance, **kw)
    return Capture(capture, layout, stack, lights, lp_path=lp_path, near=near, fits=fits, warnings=warnings,
                   corrections=corrections, checks=checks)


def _storage(opt: RunOptions) -> str:
    """How the stack holds luminance: 8-bit photographs as 8-bit sRGB codes (half the memory of
    16 bits; the normals of the synthetic JPEG scenes move by under 0.005°, BENCHMARKS.md),
    except when light intensities will rescale the samples, which 8 bits would round again."""
    return "uint16" if opt.intensities is not None or opt.reference_region is not None else "auto"


@dataclass(frozen=True)
class StackPlan:
    """Where a capture's stack goes, from its photographs' headers (:func:`plan_stack`).

    Attributes
    ----------
    stack_mb, rest_mb : float
        The stack's size and the rest of the run's peak
        (:data:`ptmcore.resources.RUN_BASE_MB` and ``RUN_BYTES_PER_PIXEL`` per pixel), MiB.
    short : bool
        A run holding the stack in memory would exceed ``memory_limit`` (by default the
        memory available now).
    on_disk : bool
        The stack goes to a file: when ``short``, and by default whenever it is
        :data:`STACK_FILE_MB` or larger; an explicit ``memory_limit`` the run fits in keeps it
        in memory.
    """

    stack_mb: float
    rest_mb: float
    short: bool
    on_disk: bool

    @property
    def peak_mb(self) -> float:
        """The run's peak: the rest, and the stack unless it goes to a file."""
        return self.rest_mb + (0.0 if self.on_disk else self.stack_mb)


def plan_stack(paths: Sequence[Path], opt: RunOptions) -> StackPlan | None:
    """The :class:`StackPlan` of a run on these photographs (1 byte per sample for JPEGs stored
    as 8-bit, 2 otherwise); None when none of the first five has a readable header."""
    # The first photograph whose header reads (a corrupt one is reported by the decoding).
    size = next(filter(None, map(image_size, paths[:5])), None)
    if size is None:
        return None
    pixels = size[0] * size[1]
    jpeg = all(p.suffix.lower() in (".jpg", ".jpeg") for p in paths)
    sample = 1 if jpeg and _storage(opt) == "auto" and opt.linearize else 2
    stack, rest = len(paths) * sample * pixels / 2**20, RUN_BASE_MB + RUN_BYTES_PER_PIXEL * pixels / 2**20
    if opt.memory_limit is not None:
        limit = opt.memory_limit
    else:
        limit = available_memory_mb()
    short = stack + rest > limit
    return StackPlan(stack, rest, short, short or (opt.memory_limit is None and stack >= STACK_FILE_MB))


def peak_memory_mb(paths: Sequence[Path], opt: RunOptions) -> float | None:
    """A bound on the peak memory (MiB) of a run on these photographs (:class:`StackPlan`);
    None when no header reads. ``reconstruct batch`` sizes its cluster by it."""
    plan = plan_stack(paths, opt)
    return None if plan is None else plan.peak_mb


def _stack_place(paths: list[Path], opt: RunOptions, scratch: str | os.PathLike | None
                 ) -> tuple[str | os.PathLike | None, list[str]]:
    """Where the stack goes (``scratch`` for a file, None for memory) and, when it goes to a
    file because memory is short, the warning that says so; decided before decoding, while
    the memory available is the run's."""
    plan = plan_stack(paths, opt) if scratch is not None else None
    if plan is None or not plan.on_disk:
        return None, []
    if not plan.short:
        return scratch, []
    limit = "--memory-limit" if opt.memory_limit is not None else "the available memory"
    return scratch, [f"the photographs' stack did not fit in {limit}: it was processed from a temporary file in "
                     "the output folder, which is slower when memory is short"]


def _ground_truth_folder(capture: Path, opt: RunOptions) -> Path | None:
    """``--ground-truth``, else ``CAPTURE/ground_truth`` when it holds normals."""
    if opt.ground_truth is not None:
        return opt.ground_truth
    guess = (capture if capture.is_dir() else capture.parent) / "ground_truth"
    return guess if os.path.lexists(guess / "normals.npy") else None


def _check_exposure(loaded: Capture, samples: np.ndarray) -> None:
    """Warn of a degenerate light layout and of photographs with many clipped pixels, mostly
    black, or brighter or darker than their light explains (``capture_checks["exposure"]``), from
    the ``samples`` of :func:`reconstruct.pipeline.defects.sampled_luminance`."""
    loaded.rank = analyse_lights(loaded.lights.directions)
    if loaded.rank.deficient:
        loaded.warnings.append(f"the PTM light matrix has rank {loaded.rank.rank} of 6: " + "; ".join(loaded.rank.causes))
    h, w = loaded.shape
    saturated = loaded.stack.saturated / (h * w)
    loaded.checks["exposure"], said = exposure_finding(samples, saturated, loaded.lights.directions,
                                                       [p.name for p in loaded.stack.paths])
    loaded.warnings += said
    if saturated.max() > CLIPPED_SHARE:
        worst = int(np.argmax(saturated))
        loaded.warnings.append(
            f"{np.count_nonzero(saturated > CLIPPED_SHARE)} photograph(s) have more than {CLIPPED_SHARE:.0%} "
            f"clipped pixels (most: {loaded.stack.paths[worst].name}, {saturated[worst]:.1%}); clipped samples are left "
            "out of photometric stereo"
        )


def load_capture(
    source: str | os.PathLike,
    options: RunOptions | None = None,
    *,
    progress: Callable[[str, int, int], None] | None = None,
    stages: Stages | None = None,
    scratch: str | os.PathLike | None = None,
) -> Capture:
    """Decode a capture and gather everything the later stages need.

    Parameters
    ----------
    source : path
        A capture folder (photographs and one ``.lp`` file), an ``.lp`` file, a
        photometric-stereo dataset folder, or a folder of photographs with glossy spheres.
    options : RunOptions, optional
        Uses ``lp``, ``linearize``, ``threads``, ``mask`` (a file; ``"auto"`` needs the normals
        and is resolved by :func:`reconstruct.pipeline.resolve_mask`), ``intensities``,
        ``intrinsics`` (sphere calibration), ``light_positions`` and ``ground_truth``.
    progress : callable, optional
        ``progress(stage, done, total)`` while the photographs are decoded.
    stages : Stages, optional
        The run's stage log (times, memory, progress); a new one when not given.
    scratch : path, optional
        A folder for the stack of a capture too large for ``options.memory_limit``
        (:func:`plan_stack`); without it the stack is always held in memory.

    Returns
    -------
    Capture

    Raises
    ------
    InputError
        For a missing or unreadable file, a malformed ``.lp``, mismatched sizes, or a capture
        whose lights cannot be found.
    """
    opt = options or RunOptions()
    stages = stages or Stages(progress)
    capture = Path(source)
    loaded = _decode(capture, _layout(capture, opt), opt, stages, scratch)
    # Photographs black or clipped everywhere, or copied over another, are refused first.
    check_content(loaded.stack)
    if opt.mask is not None and opt.mask != "auto":
        given = read_mask(opt.mask, loaded.shape)
        loaded.mask = given if loaded.mask is None or loaded.layout == PS_DATASET else given & loaded.mask
    gt_dir = _ground_truth_folder(capture, opt)
    if gt_dir is not None:
        loaded.truth, loaded.truth_source = load_ground_truth(gt_dir, loaded.shape), str(gt_dir)
    if opt.intensities is not None or opt.reference_region is not None:
        directions = loaded.lights.directions
        source = opt.intensities
        if opt.reference_region is not None:
            from ptmcore.illumination import measure_region, parse_region, reference_intensities

            source = f"reference region {opt.reference_region}"
            means, clipped = measure_region(loaded.stack, parse_region(opt.reference_region, loaded.shape))
            factors = reference_intensities(means, directions, clipped=clipped, names=loaded.stack.paths)
        elif opt.intensities == "estimate":
            factors = estimate_intensities(loaded.stack, directions, mask=loaded.mask)
        else:
            factors = read_intensities(opt.intensities, len(loaded.lights))
        loaded.stack = apply_intensities(loaded.stack, factors, relative=True, in_place=True)
        loaded.intensities = {"source": source, "factors": factors}
    samples = sampled_luminance(loaded.stack)  # one read of the stack for both findings
    _check_exposure(loaded, samples)
    if len(loaded.lights) >= 6:
        loaded.checks["stray_light"], said = stray_light_finding(samples, loaded.lights.directions,
                                                                 opt.ambient is not None)
        loaded.warnings += said
    return loaded
