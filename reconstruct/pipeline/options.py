"""Parameters of a run and of a scan comparison, checked when they are made.

Every choice is a ``Literal`` type; :func:`choices` reads its values back, so the command line
(``reconstruct.cli``) offers exactly the values the options accept, and takes its defaults from
:func:`default`. An option that does not validate raises :class:`ptmcore.errors.InputError` at
construction: a run never starts with a parameter it would reject halfway.
"""

from __future__ import annotations

import dataclasses
import math
import os
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Union

from ptmcore.errors import InputError
from ptmcore.normalmethods import FITS, NORMAL_METHODS

#: A stack this large (MiB) or larger goes to a file by default (:mod:`ptmcore.diskstack`,
#: :func:`reconstruct.pipeline.capture.plan_stack`), whatever memory is free: read from the page
#: cache it was measured as fast as in memory on 48 × 24 MP (BENCHMARKS.md), and the run's
#: resident memory drops by its size, so more runs of a batch fit side by side and a machine
#: short of memory writes it out instead of failing. Below this the stack is a small part of
#: the run's memory. Here, not in capture.py, so that the command line's help can say it.
STACK_FILE_MB = 256

__all__ = [
    "BOUNDS",
    "STACK_FILE_MB",
    "CompareOptions",
    "Align",
    "Fit",
    "Flattening",
    "Integrator",
    "NormalMethod",
    "PtmEncoding",
    "PtmFormat",
    "RunOptions",
    "ScanUnit",
    "Solver",
    "choices",
    "default",
]

#: Normal methods (:data:`ptmcore.normalmethods.NORMAL_METHODS`, where they are
#: declared); the default is the more accurate on the synthetic benchmark (BENCHMARKS.md).
NormalMethod = Literal[tuple(NORMAL_METHODS)]
#: Per-pixel fits (:data:`ptmcore.normalmethods.FITS`); the default is the more
#: accurate on the synthetic benchmark with specular highlights and shadows (BENCHMARKS.md), at
#: about three times the plain fit's time.
Fit = Literal[tuple(FITS)]
Integrator = Literal["auto", "dct", "fc", "masked", "bilateral"]
PtmFormat = Literal["lrgb", "rgb"]
#: The values a .ptm (and .rti, web/) holds: display-encoded, as viewers show them, or linear light.
PtmEncoding = Literal["srgb", "linear"]
Solver = Literal["pinv", "lstsq", "rohde"]
Flattening = Literal["plane", "poly2", "poly3", "highpass"]
#: Whether photographs displaced by the camera's drift are resampled onto one frame.
Align = Literal["auto", "off"]
#: The relighting basis published in web/ (ptmcore.bases.NAMES); auto: the one that predicts
#: left-out photographs best among the candidates.
Basis = Literal["auto", "ptm", "hsh2", "hsh3", "hsh4", "rbf", "bilinear", "neural"]
#: The candidates of ``basis="auto"`` (ptmcore.bases.CANDIDATES).
BasisCandidates = Literal["standard", "openlime", "all"]
#: What the published basis is fitted to; auto: chosen with the basis, by the same score.
BasisEncoding = Literal["auto", "srgb", "linear"]
#: What a run writes: everything, or only the relightable files (no normals, height or meshes).
Outputs = Literal["all", "relight"]
ScanUnit = Literal["mm", "cm", "m", "in"]

#: The range, inclusive, of each length (and grid spacing) a run or comparison accepts. Values
#: outside are slips (a lost decimal point, an exponent's sign) that the run cannot tell from
#: intent: 1e20 mm per pixel overflows the report's numbers, 1e-300 mm collapses the float32
#: mesh to a point. Each range is wide enough for any real photograph (1e5 pixels: more than
#: any camera or stitched panorama across, and OpenCV decodes at most 2**30 pixels).
BOUNDS: dict[str, tuple[float, float]] = {
    # mm per pixel: a nanometre (far below what light resolves, ~2e-4 mm) to 10 m (a façade
    # or an aerial photograph); float32 coordinates of 1e5 pixels keep their precision.
    "pixel_size": (1e-6, 1e4),
    # Camera to object, mm: a micrometre (closer than any lens focuses) to a kilometre.
    "distance": (1e-3, 1e6),
    # Base of the solid, in the height unit: a micrometre (no printer makes it; within
    # float32 rounding of the heights) to a kilometre.
    "solid": (1e-3, 1e6),
    # Pixels between mesh vertices: at most an image's side (see above).
    "step": (1, 100_000),
    # Wavelength in pixels: 2 is the shortest an image holds (Nyquist); beyond an image's
    # side nothing is removed, and the Gaussian's kernel grows with it (1e300 cannot be
    # allocated).
    "flatten_cutoff": (2, 100_000),
    # Threads: a thread pool of 1e12 cannot be started; a thousand is more than any machine's
    # cores that one run would use.
    "threads": (1, 1024),
    # Comparison distances, mm: a nanometre (below any scanner's resolution) to a kilometre.
    "tolerance": (1e-6, 1e6),
    "max_distance": (1e-6, 1e6),
}


def _flag(name: str) -> str:
    """What an option is called in messages: its command-line spelling."""
    return "--" + name.replace("_", "-")


def _literal_values(hint: object) -> tuple | None:
    """The values of a ``Literal`` type, or of ``Literal | None``; None for any other type
    (``Path | Literal["auto"]`` takes any path, so it is no choice)."""
    if typing.get_origin(hint) is Literal:
        return typing.get_args(hint)
    if typing.get_origin(hint) in (Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1 and typing.get_origin(args[0]) is Literal:
            return typing.get_args(args[0])
    return None


def choices(options: type, name: str) -> tuple[str, ...]:
    """The values option ``name`` of the dataclass ``options`` accepts (its ``Literal`` type).

    >>> choices(RunOptions, "normals")
    ('ps', 'ptm', 'ptm-debiased')
    """
    values = _literal_values(typing.get_type_hints(options)[name])
    if values is None:
        raise TypeError(f"{options.__name__}.{name} is not a choice")
    return values


def default(options: type, name: str) -> object:
    """The default value of option ``name`` of the dataclass ``options``."""
    return next(f.default for f in dataclasses.fields(options) if f.name == name)


def _check_choices(options: object) -> None:
    """Every ``Literal``-typed field of ``options`` holds one of its values."""
    hints = typing.get_type_hints(type(options))
    for f in dataclasses.fields(options):
        values = _literal_values(hints[f.name])
        value = getattr(options, f.name)
        if values is not None and value is not None and value not in values:
            raise InputError(f"{_flag(f.name)}: unknown value {value!r}; choose from {', '.join(values)}")


def _positive(options: object, *names: str, unit: str = "") -> None:
    """Each of ``names`` is None or a positive finite number."""
    for name in names:
        value = getattr(options, name)
        if value is not None and not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise InputError(f"{_flag(name)} must be a positive number{unit}, got {value}")


def _within(options: object, name: str, unit: str) -> None:
    """Option ``name`` is None or a positive number within its range in :data:`BOUNDS`;
    ``unit`` (a plural noun) is named in the message."""
    _positive(options, name, unit=f" of {unit}")
    value = getattr(options, name)
    low, high = BOUNDS[name]
    if value is not None and not low <= value <= high:
        shown = f"{value:g}" if isinstance(value, float) else value
        raise InputError(f"{_flag(name)} must be between {low:g} and {high:g} {unit}, got {shown}")


def _path_or_word(value: object, words: tuple[str, ...], name: str) -> Path | str | None:
    """A path option that also takes keywords (``"auto"``, ``"none"``): keywords stay strings.

    An empty path is refused: ``Path("")`` is the current folder, which the user never meant.
    """
    if value is None or (isinstance(value, str) and value in words):
        return value
    if isinstance(value, (str, os.PathLike)) and os.fspath(value) == "":
        raise InputError(f"{_flag(name)} is an empty path; give a file name")
    return Path(value)


def _check_pairs(options: RunOptions) -> None:
    """Options that would do nothing without another, or cannot go with it: an error rather
    than a run that silently ignores what the user asked for."""
    if options.distance is not None and options.intrinsics is None:
        raise InputError("--distance needs --intrinsics: it scales a perspective camera's depths to "
                         "millimetres (for the default orthographic camera give --pixel-size)")
    if options.flatten != "highpass" and options.flatten_cutoff != default(RunOptions, "flatten_cutoff"):
        raise InputError("--flatten-cutoff needs --flatten highpass: the other flattenings have no cutoff")
    if options.intrinsics is not None and options.integrator == "fc":
        # Checked here too so that the run refuses before it decodes a photograph.
        raise InputError("--integrator fc cannot integrate through a perspective camera (--intrinsics): "
                         "choose masked, bilateral, dct or auto")


@dataclass
class RunOptions:
    """Parameters of :func:`reconstruct.pipeline.run_capture`; checked on construction.

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
    integrator : {"auto", "dct", "fc", "masked", "bilateral"}
        Least squares on the mask only ("masked", conjugate gradients preconditioned by the
        bounding box's DCT solver), the same with bilateral weights that keep steps sharp
        ("bilateral"), Poisson with Neumann boundary by DCT on the whole frame ("dct"), or
        Frankot–Chellappa. "auto" (:func:`reconstruct.surface.choose.integrate_auto`): with a
        mask of at most a megapixel, bilateral where it finds depth steps in the normals, else
        masked weighed by nz²; masked for a larger mask; dct without one.
    step : int or None
        Mesh subsampling; None picks the smallest step that keeps the mesh under
        :data:`reconstruct.pipeline.stages.AUTO_MESH_VERTICES` vertices.
    linearize : bool
        Take 8-bit photographs as sRGB and linearise them (for the normals; the ``.ptm`` file
        holds what ``ptm_encoding`` says).
    ptm_format : {"lrgb", "rgb"}
        Format of ``coefficients.ptm``: one luminance polynomial and a colour per pixel, or
        one polynomial per channel.
    basis : {"auto", "ptm", "hsh2", "hsh3", "hsh4", "rbf", "bilinear", "neural"}
        The relighting basis of ``web/`` (the page, OpenLIME's files), the report's relit
        pictures and ``reconstruct relight`` (:mod:`ptmcore.bases`). ``"auto"`` (default): the
        candidate (``basis_candidates``) that predicts each photograph left out of its fit
        best, measured on the capture.
    basis_candidates : {"standard", "openlime", "all"}
        What ``"auto"`` chooses from (:data:`ptmcore.bases.CANDIDATES`): every basis fitted in
        seconds (default; ``hsh4`` is shown by this project's page, not by OpenLIME), those
        OpenLIME shows too, or all of them with the learned ``neural`` basis (its training
        adds tens of seconds, whatever the image size).
    basis_encoding : {"auto", "srgb", "linear"}
        What the published basis is fitted to: the photographs display-encoded (as relight and
        RTIBuilder fit them), or linear light, which the page encodes for display; ``"auto"``:
        chosen with the basis by the same measure (8-bit linear planes lose the shadows' levels).
    outputs : {"all", "relight"}
        ``"relight"``: only the relightable files (``coefficients.ptm``, ``web/``) and the
        report, without normals, height or meshes — seconds instead of minutes.
    ptm_encoding : {"srgb", "linear"}
        What ``coefficients.ptm`` and ``coefficients.rti`` hold: the photographs
        display-encoded as sRGB, as viewers (RTIViewer, OpenLIME) show them, whatever their bit
        depth (8-bit sRGB photographs as they are, as HP's PTMfitter fits them; 16-bit and float
        ones encoded), or linear light, for those who compute with the files.
    solver : {"pinv", "lstsq", "rohde"}
        The {1}-inverse of the PTM light matrix (ptmcore.solvers); pinv gives the
        least-squares, minimum-norm fit.
    loo : bool
        Measure how well each relighting basis (PTM, HSH of orders 2–4, RBF, bilinear) predicts every
        photograph left out of its fit: ``loo_<basis>.tif`` maps and their RMS in report.json.
    fit : {"lobe", "irls", "trimmed", "plain"}
        How each pixel's samples are weighted: robustly (Tukey IRLS, or 0/1 trimming, leaving
        out shadowed, clipped and specular samples) or by plain least squares. ``"lobe"`` is
        IRLS with a glossy reflectance lobe shared by the object, estimated from the photographs
        and used where it explains them (:mod:`ptmcore.lobe`); for PTM normals it is IRLS.
    hsh : bool
        Also write ``coefficients.rti``: hemispherical harmonics of order 3, RTIViewer's HSH
        format, fitted per channel to the photographs as encoded.
    flatten : {"plane", "poly2", "poly3", "highpass"} or None
        Remove low-frequency bending of the height map (from errors in the light directions):
        a plane, a polynomial of order 2 or 3, or wavelengths above ``flatten_cutoff`` pixels.
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
        See ``intrinsics``; only with ``intrinsics``.
    flatten_cutoff : float
        For ``flatten="highpass"`` (and only with it): the wavelength in pixels that keeps half
        its amplitude.
    intensities : str or None
        Per-photograph light intensities: a file (one value or ``r g b`` per photograph, in
        ``.lp`` order) or ``"estimate"`` to estimate them from the photographs; each
        photograph is divided by its light's intensity before the normals are estimated.
    mask : Path, "auto" or None
        Image whose non-zero pixels are the object, or ``"auto"`` to segment the object from
        its albedo and normals (:func:`reconstruct.surface.foreground_mask`); height and mesh
        are restricted to it.
    threads : int or None
        Threads decoding the photographs, running the per-pixel fits, integrating and writing
        the files (default: every CPU the process may use, :func:`ptmcore.resources.cpu_count`).
    memory_limit : float or None
        Megabytes the run may hold in memory: the stack stays in memory when the whole run fits
        in it, else it is a memory-mapped file in the staging folder whose pages leave the
        process band by band (:mod:`ptmcore.diskstack`). Default (None): a stack of
        ``STACK_FILE_MB`` (256 MB) or more always goes to the file, a smaller one when the run
        would not fit in the memory available (:func:`ptmcore.resources.available_memory_mb`:
        a cluster job's or container's cgroup included;
        :func:`reconstruct.pipeline.capture.plan_stack`).
    ground_truth : Path or None
        Folder with ``normals.npy`` (and ``mask.png``, ``height.npy``) to measure accuracy;
        default: ``CAPTURE/ground_truth`` when it exists.
    light_positions : Path, "auto" or "none"
        Near (point) lights: a light-position file (``name,x,y,z`` in pixels,
        :func:`ptmcore.nearlight.read_light_positions`) whose positions give every pixel its
        own light direction and inverse-square falloff. ``"auto"``: the file
        ``light_positions.csv`` beside the ``.lp`` when there is one, or, for a capture
        calibrated from two or more spheres, the lights triangulated from their highlights
        when they are near (:func:`reconstruct.calibration.lights_are_near`). ``"none"``:
        distant lights, one direction per photograph.
    align : {"auto", "off"}
        ``"auto"``: the camera's drift is measured (:mod:`ptmcore.align`) and the photographs
        resampled onto one frame when one is displaced by more than
        :data:`ptmcore.align.ALIGN_THRESHOLD_PX` (default; the measurement costs about 0.2 s
        on a steady capture). ``"off"``: measured and reported, not undone.
    ambient : Path or None
        A photograph of the object with the lamps off (the room's light alone, same exposure),
        subtracted from every photograph in linear light.
    flat_field : Path or None
        A folder with a capture of a flat white or grey board under the same lights (same
        ``.lp`` names, or the same order): each photograph is divided by its light's smooth gain
        over the frame (:func:`ptmcore.illumination.load_flat_field`).
    reference_region : str or None
        ``"x,y,w,h"`` (pixels; x the column and y the row of the top-left corner): a grey card
        seen in every photograph, from which each photograph's light intensity is read
        (:func:`ptmcore.illumination.reference_intensities`); not with ``intensities``.

    Raises
    ------
    InputError
        On construction (and on :func:`dataclasses.replace`), for a value the run would reject:
        a length or step outside its range in :data:`BOUNDS`, an empty path, or an option that
        does nothing without another (``distance`` without ``intrinsics``, ``flatten_cutoff``
        without ``flatten="highpass"``) or cannot go with it (``integrator="fc"`` with
        ``intrinsics``, ``decimate`` with ``max_error``).
    """

    lp: Path | None = None
    pixel_size: float | None = None
    normals: NormalMethod = "ps"
    integrator: Integrator = "auto"
    step: int | None = None
    linearize: bool = True
    ptm_format: PtmFormat = "lrgb"
    ptm_encoding: PtmEncoding = "srgb"
    solver: Solver = "pinv"
    loo: bool = False
    fit: Fit = "lobe"
    hsh: bool = False
    flatten: Flattening | None = None
    decimate: int | None = None
    max_error: float | None = None
    solid: float | None = None
    glb: bool = False
    intrinsics: str | None = None
    distance: float | None = None
    flatten_cutoff: float = 200.0
    intensities: str | None = None
    mask: Path | Literal["auto"] | None = None
    threads: int | None = None
    memory_limit: float | None = None
    ground_truth: Path | None = None
    light_positions: Path | Literal["auto", "none"] = "auto"
    align: Align = "auto"
    ambient: Path | None = None
    flat_field: Path | None = None
    reference_region: str | None = None
    basis: Basis = "auto"
    basis_candidates: BasisCandidates = "standard"
    basis_encoding: BasisEncoding = "auto"
    outputs: Outputs = "all"

    def __post_init__(self) -> None:
        _check_choices(self)
        for name in ("step", "decimate", "threads"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int) and value >= 1):
                raise InputError(f"{_flag(name)} must be a whole number of at least 1, got {value}")
        _within(self, "pixel_size", "millimetres")
        _within(self, "distance", "millimetres")
        _within(self, "solid", "height units")
        _within(self, "step", "pixels")
        _within(self, "flatten_cutoff", "pixels")
        _within(self, "threads", "threads")
        _positive(self, "max_error", "memory_limit")
        if self.decimate is not None and self.max_error is not None:
            raise InputError("give either a triangle count to decimate to or a maximum error, not both")
        if self.intrinsics is not None:
            from reconstruct.calibration.camera import parse_intrinsics

            try:
                parse_intrinsics(self.intrinsics)
            except ValueError as exc:
                raise InputError(f"--intrinsics: {exc}") from None
        _check_pairs(self)
        if isinstance(self.intensities, str) and not self.intensities:
            raise InputError("--intensities is an empty path; give a file name or 'estimate'")
        self.lp = _path_or_word(self.lp, (), "lp")
        self.ground_truth = _path_or_word(self.ground_truth, (), "ground_truth")
        self.mask = _path_or_word(self.mask, ("auto",), "mask")
        self.light_positions = _path_or_word(self.light_positions, ("auto", "none"), "light_positions")
        self.ambient = _path_or_word(self.ambient, (), "ambient")
        self.flat_field = _path_or_word(self.flat_field, (), "flat_field")
        if self.reference_region is not None:
            if self.intensities is not None:
                raise InputError("give either --intensities or --reference-region: both set each photograph's "
                                 "light intensity")
            from ptmcore.illumination import parse_region

            parse_region(self.reference_region, (1 << 30, 1 << 30))  # its form; the frame once decoded


@dataclass
class CompareOptions:
    """Parameters of :func:`reconstruct.pipeline.run_compare` (``reconstruct compare``).

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

    Raises
    ------
    InputError
        On construction, for a value the comparison would reject: a distance outside its range
        in :data:`BOUNDS`, ``min_fraction`` without ``tolerance``, ``scale`` with ``no_align``.
    """

    scan_units: ScanUnit = "mm"
    scale: bool = False
    initial: Path | None = None
    no_align: bool = False
    tolerance: float | None = None
    min_fraction: float = 0.95
    reverse: bool = False
    max_distance: float | None = None

    def __post_init__(self) -> None:
        _check_choices(self)
        _within(self, "tolerance", "millimetres")
        _within(self, "max_distance", "millimetres")
        if not (isinstance(self.min_fraction, (int, float)) and 0 < self.min_fraction <= 1):
            raise InputError(f"the fraction needed within tolerance must be in (0, 1], got {self.min_fraction}")
        # Options that would be silently ignored without their partner (see _check_pairs).
        if self.tolerance is None and self.min_fraction != default(CompareOptions, "min_fraction"):
            raise InputError("--min-fraction needs --tolerance: it is the share of points that must be "
                             "within the tolerance")
        if self.no_align and self.scale:
            raise InputError("--scale does nothing with --no-align: the scale is estimated by the alignment")
        self.initial = _path_or_word(self.initial, (), "initial")
