"""``reconstruct compare`` (and ``run --scan``): a laser scan against a reconstruction, written out.

The measurement itself is :mod:`reconstruct.compare` (loading, alignment, distances, figures);
this module reads the inputs, writes ``comparison.json``, ``distances.ply``, ``histogram.png``,
``overlay.png`` and ``report.html`` through a staged output folder.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptmcore.errors import InputError, read_input_text
from reconstruct.pipeline.options import CompareOptions
from reconstruct.pipeline.profiling import ProgressFn, Stages
from reconstruct.pipeline.report import AlignmentSummary, CompareReport, ToleranceTest
from reconstruct.pipeline.staging import StagedOutput, staged_output
from reconstruct.report import outputs
from reconstruct.report.html import write_report_html

__all__ = ["COMPARISON_FILES", "CompareResult", "ScanStep", "compare_into", "run_compare"]

SIGN_CONVENTION = "positive: the scan lies on the camera side of the reconstruction"


@dataclass
class CompareResult:
    """What :func:`run_compare` produced: the folder, its files and the report."""

    output: Path
    files: dict[str, Path]
    report: CompareReport

    @property
    def passed(self) -> bool | None:
        """Whether the tolerance test passed; None without a tolerance."""
        return self.report.passed


#: The most bytes read of an initial transform: sixteen numbers and comments fit in far less.
TRANSFORM_MAX_BYTES = 64 << 10


def _read_initial(path: Path) -> np.ndarray:
    """The 4×4 initial transform of a text file: four lines of four numbers, ``#`` comments."""
    text = read_input_text(path, "initial transform", max_bytes=TRANSFORM_MAX_BYTES)
    if not any(line.split("#")[0].strip() for line in text.splitlines()):
        # numpy would warn on stderr and return an empty array.
        raise InputError("the initial transform holds no numbers (a 4×4 matrix is expected)", path)
    try:
        m = np.loadtxt(io.StringIO(text), dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"cannot read the initial transform ({exc})", path) from None
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise InputError(f"the initial transform must be a 4×4 matrix of numbers, got shape {m.shape}", path)
    return m


def _reconstruction_mesh(path: Path) -> Path:
    """The mesh to compare: ``path`` itself, or an output folder's mesh.ply, which must be in mm."""
    if not path.is_dir():
        return path
    report_file = path / "report.json"
    if report_file.exists():
        try:
            unit = json.loads(read_input_text(report_file, "report.json")).get("height_unit")
        except (ValueError, AttributeError):  # not JSON, or not an object
            raise InputError("not a report.json of reconstruct run (damaged?)", report_file) from None
        if unit != "mm":
            from reconstruct.report.summary import unit_words

            raise InputError(f"this reconstruction's heights are in {unit_words(unit)}, not mm: run it with "
                             "--pixel-size", path)
    return path / "mesh.ply"


def _write_figures(staged: StagedOutput, rec, result, tolerance: float | None,
                   warnings: list[str]) -> tuple[list[str], float]:
    """distances.ply, histogram.png and (where the machine can render) overlay.png; returns
    their names and the colour range (± mm) they share."""
    from reconstruct.compare import default_limit, write_distance_ply, write_histogram, write_overlay

    d = result.signed[result.mask]
    limit = default_limit(d)
    on_scan = np.where(result.mask, result.signed, np.nan)
    if rec.faces is not None and result.reverse is not None:
        # The reconstruction's distance to the scan, with the scan's sign convention
        # (positive: the scan lies on the camera side).
        shown = np.where(result.reverse_mask, -result.reverse, np.nan)
        write_distance_ply(staged / "distances.ply", rec.points, rec.faces, shown, limit)
    else:
        shown = on_scan
        write_distance_ply(staged / "distances.ply", result.aligned_points, None, on_scan, limit)
    write_histogram(staged / "histogram.png", d, result.stats, tolerance=tolerance)
    names = ["distances.ply", "histogram.png"]
    if rec.faces is None:
        warnings.append("no overlay.png: the reconstruction is a point cloud")
        return names, limit
    try:
        write_overlay(staged / "overlay.png", rec.points, rec.faces, result.aligned_points, shown, limit)
        names.append("overlay.png")
    except RuntimeError as exc:
        warnings.append(f"no overlay.png: {exc}")
    return names, limit


def _comparison_report(rec_path: Path, scan: Path, opt: CompareOptions, alignment, result,
                       limit: float, fraction: float | None, warnings: list[str]) -> CompareReport:
    """What comparison.json says."""
    tolerance = None if fraction is None else ToleranceTest(
        opt.tolerance, fraction, opt.min_fraction, bool(fraction >= opt.min_fraction))
    return CompareReport(
        str(rec_path.resolve()), str(scan.resolve()), {"distances": "mm", "scan_input": opt.scan_units},
        {f.name: getattr(opt, f.name) for f in dataclasses.fields(opt)},
        AlignmentSummary.from_alignment(alignment), result.stats, result.reverse_stats,
        tolerance, [-limit, limit], SIGN_CONVENTION, warnings=warnings,
    )


def _scan_progress(progress: ProgressFn | None) -> ProgressFn | None:
    """``progress`` with the comparison's stages named ``scan_*``: within ``run --scan`` they
    follow the run's own, some of the same names (``write``, ``report``)."""
    if progress is None:
        return None
    return lambda stage, done, total: progress(f"scan_{stage}", done, total)


def run_compare(
    reconstruction: str | os.PathLike,
    scan: str | os.PathLike,
    output: str | os.PathLike,
    options: CompareOptions | None = None,
    *,
    progress: ProgressFn | None = None,
) -> CompareResult:
    """Align a scan to a reconstruction, measure their distances and write the comparison.

    ``reconstruction`` is a mesh or an output folder of ``reconstruct run`` (its mesh.ply,
    which must be in millimetres). Writes ``comparison.json``, ``distances.ply`` (the
    reconstruction coloured by its distance to the scan, or the scan points when the
    reconstruction is a point cloud), ``histogram.png``, ``overlay.png`` (an off-screen
    render; skipped with a warning where the machine cannot render) and ``report.html``
    (with the reconstruction's own report when it is an output folder). Written into an
    earlier result (``output`` is the reconstruction's own folder), the result's other files
    are kept and those of an earlier comparison replaced, in one step (:func:`staged_output`).
    ``progress(stage, done, total)`` is called as the stages advance: ``scan_read``,
    ``scan_align``, ``scan_distances``, ``scan_write`` (the figures), ``scan_report``.
    """
    from reconstruct.compare import load_geometry

    opt = options or CompareOptions()
    given = Path(reconstruction)
    stages = Stages(_scan_progress(progress))
    # Every input is read before the output folder is touched.
    with stages("read", 2) as advance:
        rec_path = _reconstruction_mesh(given)
        rec = load_geometry(rec_path)
        advance(1)
        scan_geometry = load_geometry(scan, units=opt.scan_units)
    initial = _read_initial(opt.initial) if opt.initial is not None else None
    with staged_output(output) as staged:
        kept = staged.keep_existing(exclude=COMPARISON_FILES)
        names, report = compare_into(staged, rec, rec_path, scan_geometry, Path(scan), opt, initial=initial,
                                     also=[given] if given.is_dir() else [],
                                     stages=stages)
        files = staged.publish([*kept, *names])
    return CompareResult(staged.output, files, report)


#: Every file a comparison may write: what a new comparison replaces in a result folder.
COMPARISON_FILES = ("distances.ply", "histogram.png", "overlay.png", "comparison.json", "report.html")


def compare_into(staged: StagedOutput, rec, rec_path: Path, scan_geometry, scan: Path, opt: CompareOptions, *,
                 initial: np.ndarray | None = None, also: list[Path] | None = None, page: dict | None = None,
                 stages: Stages | None = None) -> tuple[list[str], CompareReport]:
    """Compare a loaded scan with a loaded reconstruction and write the comparison's files
    into ``staged`` (``run --scan`` calls it before the run's files are published, so the
    reconstruction and its comparison appear together). ``also``: folders whose report.json
    the page shows beside the comparison; ``page``: the run's own page's arguments (its report,
    previews, thumbnails: :data:`reconstruct.pipeline.run.Then`), so nothing is read back;
    ``stages``: the comparison's stage timer and progress (:func:`run_compare`'s, with its
    reading of the inputs), a fresh one by default. Returns the files' names and the report."""
    from reconstruct.compare import align, distances, within_tolerance

    stages = stages or Stages()
    warnings: list[str] = []
    with stages("align", 3) as advance:
        alignment = align(rec, scan_geometry, scale=opt.scale, initial=initial, no_align=opt.no_align,
                          progress=advance)
    with stages("distances"):
        result = distances(rec, scan_geometry, alignment, reverse=opt.reverse or rec.faces is not None,
                           max_distance=opt.max_distance)
    with stages("write"):
        names, limit = _write_figures(staged, rec, result, opt.tolerance, warnings)
    fraction = within_tolerance(result, opt.tolerance) if opt.tolerance is not None else None
    report = _comparison_report(rec_path, scan, opt, alignment, result, limit, fraction, warnings)
    report.stages = stages.timer.stages  # the same dict: the page's own time joins it
    # The page also shows the reconstruction's report; comparison.json follows it, with its time.
    with stages("report"):
        write_report_html(staged.staging, comparison=report.to_dict(), also=also or [], **(page or {}))
    outputs.write_json(staged / "comparison.json", report.to_dict())
    return [*names, "comparison.json", "report.html"], report


class ScanStep:
    """The comparison of ``run --scan`` (and a batch's scan column) as the last step of a run.

    Made before the run, it reads the scan, so an unreadable scan stops the run before any
    output. Passed as ``run(..., then=step)``, it compares the scan with the staged
    ``mesh.ply`` and writes its files beside the run's, the page of both among them, published
    together. When the
    comparison itself fails (no overlap, say) the reconstruction is still published with its
    own page, and :meth:`result` raises the comparison's error after it.

    Parameters
    ----------
    scan : path
        The scan file.
    options : CompareOptions, optional
    progress : callable, optional
        ``progress(stage, done, total)``: reading the scan (``scan_read``) now, the rest of
        :func:`run_compare`'s stages when the step runs.
    """

    def __init__(self, scan: str | os.PathLike, options: CompareOptions | None = None, *,
                 progress: ProgressFn | None = None) -> None:
        from reconstruct.compare import load_geometry

        self.scan = Path(scan)
        self.options = options or CompareOptions()
        self.stages = Stages(_scan_progress(progress))  # its reading's time joins comparison.json's
        with self.stages("read"):
            self.geometry = load_geometry(self.scan, units=self.options.scan_units)
        self.report: CompareReport | None = None
        self.error: InputError | None = None

    def __call__(self, staged: StagedOutput, page: dict) -> list[str]:
        from reconstruct.compare import load_geometry

        try:
            names, self.report = compare_into(staged, load_geometry(staged / "mesh.ply"), staged.output / "mesh.ply",
                                              self.geometry, self.scan, self.options, page=page,
                                              stages=self.stages)
        except InputError as exc:
            self.error = exc
            write_report_html(staged.staging, **page)
            return ["report.html"]
        return names

    def result(self, output: Path, files: dict[str, Path]) -> CompareResult:
        """The comparison written into the published ``output``; raises its error if it failed."""
        if self.error is not None:
            raise self.error
        return CompareResult(output, files, self.report)
