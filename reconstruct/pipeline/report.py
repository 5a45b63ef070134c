"""The report of a run: typed here, written as ``report.json``.

A run fills a :class:`RunReport`; :meth:`RunReport.to_dict` gives the JSON document, whose keys
are part of the output interface (README, "report.json"): later versions add keys, never
rename them. Readers of ``report.json`` files (report.html, the preview, ``compare``) read the
JSON, which may come from an older version, so they treat every key as optional.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata as md
import math
import platform
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import ptmcore
from ptmcore.solvers import RankInfo

__all__ = [
    "Accuracy",
    "CaptureInputs",
    "LightLayout",
    "LightModel",
    "MeshFacts",
    "NormalMapInputs",
    "PtmInputs",
    "PtmSummary",
    "RunReport",
    "json_safe",
    "versions",
]

#: Fields written only when they hold a value.
_OPTIONAL = {"omit_if_none": True}


def json_safe(value: Any) -> Any:
    """``value`` as plain JSON data: dataclasses become dicts (fields marked optional are left
    out when None), NumPy scalars and arrays Python numbers and lists, paths strings, and
    non-finite floats None (JSON has no NaN or infinity)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: json_safe(getattr(value, f.name)) for f in dataclasses.fields(value)
                if not (f.metadata.get("omit_if_none") and getattr(value, f.name) is None)}
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def versions() -> dict[str, str]:
    """Versions of Python, this package and the libraries whose results it reports."""
    out = {"python": platform.python_version(), "ptm-reconstruct": ptmcore.__version__}
    for pkg in ("numpy", "scipy", "simplejpeg", "opencv-python-headless", "tifffile", "trimesh"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    return out


@dataclass
class CaptureInputs:
    """What a capture run read."""

    capture: str
    lp: str | None
    layout: str
    photographs: int
    width: int
    height: int
    bit_depth: int
    mask: str | None
    #: Where the stack was held: "memory", or "file" (:func:`reconstruct.pipeline.capture.plan_stack`).
    stack: str = "memory"


@dataclass
class PtmInputs:
    """What a run from an existing ``.ptm`` file read."""

    ptm: str
    format: str
    width: int
    height: int
    mask: str | None


@dataclass
class NormalMapInputs:
    """What a run from a normal map (``reconstruct integrate``) read."""

    normal_map: str
    width: int
    height: int
    mask: str | None


@dataclass
class MeshFacts:
    """The height map's integration and the mesh made from it."""

    vertices: int
    faces: int
    unit: str
    step: int
    integrator: str
    integrator_reason: str
    decimation: dict | None = None


@dataclass
class LightLayout:
    """Rank and conditioning of the PTM light matrix (:func:`ptmcore.solvers.analyse_lights`)."""

    rank: int
    condition: float | None
    singular_values: list[float]
    tolerance: float
    causes: list[str]

    @classmethod
    def from_rank(cls, rank: RankInfo) -> LightLayout:
        return cls(rank.rank, rank.condition if math.isfinite(rank.condition) else None,
                   list(np.asarray(rank.singular_values, dtype=float)), float(rank.tolerance), list(rank.causes))


@dataclass
class LightModel:
    """Distant lights (one direction per photograph) or near point lights."""

    type: str
    source: str | None = field(default=None, metadata=_OPTIONAL)
    median_distance_px: float | None = field(default=None, metadata=_OPTIONAL)
    detail: str = ""


@dataclass
class PtmSummary:
    """``coefficients.ptm``: format, size, encoding and the 8-bit quantisation error.

    The PTM is fitted to the photographs as they are encoded: sRGB for 8-bit photographs,
    linear light (scaled to 0-255) for 16-bit ones, which viewers then show dark; the preview
    and report.html encode a linear PTM's renderings as sRGB for display.
    """

    format: str
    width: int
    height: int
    scale: list[float]
    bias: list[int]
    bytes: int
    max_error: list[float]
    rms_error: list[float]
    clipped: list[int]
    encoding: str
    hsh_rti: dict | None = field(default=None, metadata=_OPTIONAL)
    error_unit: str = "coefficient units (luminance 0-255)"

    @classmethod
    def from_written(cls, written: dict, encoding: str, hsh: dict | None = None) -> PtmSummary:
        """From what :func:`ptmcore.ptmfile.write_ptm` (and ``write_rti_hsh``) returned, for
        files in ``encoding`` ("srgb" or "linear", :attr:`RunOptions.ptm_encoding`)."""
        keep = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in written.items() if k in keep},
                   encoding="sRGB" if encoding == "srgb" else "linear",
                   hsh_rti=None if hsh is None else {k: v for k, v in hsh.items() if k != "path"})


@dataclass
class Accuracy:
    """Errors against ground truth: normals (degrees) and, with a pixel size, heights (mm)."""

    ground_truth: str
    normals: dict[str, float]
    height_rmse_mm: float | None = field(default=None, metadata=_OPTIONAL)


@dataclass
class RunReport:
    """Everything ``report.json`` says of a run.

    The capture-only sections (``capture_checks`` … ``leave_one_out``) are written for runs from
    photographs; runs from a ``.ptm`` file or a normal map have no such sections.
    ``peak_rss_mb`` is the whole run's peak: the largest of the stages' peaks, as sampled.
    ``seconds`` is the run's wall-clock time up to ``report.json``: the stages' times add up to
    more, since the files are written (stage ``write``) while later stages compute.
    """

    inputs: CaptureInputs | PtmInputs | NormalMapInputs
    parameters: dict[str, Any]
    height_unit: str
    mesh: MeshFacts | None
    stages: dict[str, dict[str, float]]
    peak_rss_scope: str
    warnings: list[str]
    accuracy: Accuracy | None = None
    peak_rss_mb: float | None = None
    albedo_scale: float | None = None
    lights: LightLayout | None = None
    light_model: LightModel | None = None
    intensities: dict | None = None
    reflectance_lobe: dict | None = None
    ptm: PtmSummary | None = None
    leave_one_out: dict | None = None
    capture_checks: dict | None = None
    relighting: dict | None = None
    versions: dict[str, str] = field(default_factory=versions)
    fingerprint: str | None = None
    seconds: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """The ``report.json`` document, keys in their documented order.

        ``fingerprint`` (of the inputs and options, :func:`reconstruct.batch.fingerprint`) is
        written last, and only by a batch, which uses it to skip finished objects.
        """
        keys = ["inputs", "parameters", "height_unit"]
        if isinstance(self.inputs, CaptureInputs):
            keys += ["capture_checks", "albedo_scale", "lights", "light_model", "intensities", "reflectance_lobe", "ptm",
                     "relighting", "leave_one_out"]
        keys += ["accuracy", "mesh", "seconds", "stages", "peak_rss_mb", "peak_rss_scope", "versions", "warnings"]
        if self.fingerprint is not None:
            keys.append("fingerprint")
        return {k: json_safe(getattr(self, k)) for k in keys}


@dataclass
class AlignmentSummary:
    """How the scan was brought onto the reconstruction (:class:`reconstruct.compare.Alignment`)."""

    transform_scan_to_reconstruction: list[list[float]]
    scale: float
    fitness: float
    inlier_rmse_mm: float
    method: list[str]

    @classmethod
    def from_alignment(cls, alignment) -> AlignmentSummary:
        return cls(np.asarray(alignment.transform, dtype=float).tolist(), float(alignment.scale),
                   float(alignment.fitness), float(alignment.inlier_rmse), list(alignment.method))


@dataclass
class ToleranceTest:
    """The share of scan points within a tolerance, and whether it is enough."""

    tolerance_mm: float
    fraction_within: float
    min_fraction: float
    passed: bool


@dataclass
class CompareReport:
    """Everything ``comparison.json`` says of a scan comparison (keys: README, "Comparing with
    a laser scan")."""

    reconstruction: str
    scan: str
    units: dict[str, str]
    parameters: dict[str, Any]
    alignment: AlignmentSummary
    statistics_mm: dict[str, float]
    reverse_statistics_mm: dict[str, float] | None
    tolerance: ToleranceTest | None
    colour_range_mm: list[float]
    sign_convention: str
    stages: dict[str, dict[str, float]] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=versions)
    warnings: list[str] = field(default_factory=list)

    @property
    def passed(self) -> bool | None:
        """Whether the tolerance test passed; None without one."""
        return None if self.tolerance is None else self.tolerance.passed

    def to_dict(self) -> dict[str, Any]:
        """The ``comparison.json`` document."""
        return json_safe(self)
