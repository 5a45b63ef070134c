"""Running a batch on Dask's distributed scheduler, one object per task.

Each object runs in a Dask worker as :func:`run_object`: skipped when its folder is complete
and its fingerprint unchanged, else reconstructed by :func:`reconstruct.pipeline.run` (and
compared with its scan), with every failure turned into a ``failed`` row. :func:`run_batch`
starts a local cluster sized for this machine's memory, or uses an existing one, holds a lock
on the output folder, and writes ``batch.csv``, ``batch.json`` and ``index.html``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import shutil
import time
from contextlib import ExitStack
from pathlib import Path

from ptmcore.errors import InputError
from reconstruct.batch.rows import DONE, FAILED, SKIPPED, BatchItem, BatchRow
from reconstruct.pipeline.report import json_safe

__all__ = ["BatchStopped", "choose_workers", "estimate_peak_mb", "fingerprint", "is_complete", "run_object",
           "stop_objects"]

#: Fingerprint format; a new one makes every object run again.
_FINGERPRINT_VERSION = 1

#: The batches stopped in this process (their ``token``s): see :func:`stop_objects`.
_STOPPED: set[str] = set()


class BatchStopped(BaseException):
    """Raised inside an object's run when its batch was stopped (:func:`stop_objects`).

    A BaseException, as KeyboardInterrupt is: the run's handlers of ``Exception`` (a picture
    that cannot be made becomes a note on the page) must not take it for a failure of theirs.
    """


def stop_objects(token: str) -> None:
    """Stop the objects of batch ``token`` running in this process (a Dask worker's: the
    batch's process runs this on every worker when it is interrupted).

    Each such run stops at its next step of progress (a photograph decoded, a band of
    normals, a stage begun), by raising :class:`BatchStopped` from there; its hidden staging
    folder is removed as for any failed run, and its earlier result stays as it was. Objects of
    other batches on the same workers go on. A run cannot be stopped from outside its own
    thread any sooner in Python, and killing the worker would leave the staging folder behind.
    """
    _STOPPED.add(token)


def _stop_when_asked(token: str | None):
    """The progress callback of a run of batch ``token``: it raises once the batch is stopped."""
    if token is None:
        return None

    def progress(stage: str, done: int, total: int) -> None:
        if token in _STOPPED:
            raise BatchStopped(f"the batch was stopped during the {stage} stage")

    return progress


def _file_facts(path: Path) -> list:
    stat = path.stat()
    return [path.name, stat.st_size, stat.st_mtime_ns]


def fingerprint(item: BatchItem) -> str:
    """A hash of what an object's result depends on: the names, sizes and modification times of
    its files, the content of its ``.lp`` files, its options and its scan.

    A changed photograph, light file, option or scan gives another fingerprint, so a batch run
    again redoes that object and skips the others.
    """
    import ptmcore

    source = item.source
    if source.is_dir():
        files = sorted(p for p in source.iterdir() if p.is_file())
    else:
        files = [source, *sorted(p for p in source.parent.glob("*.lp"))] if source.suffix.lower() == ".lp" else [source]
    facts = {
        "version": [_FINGERPRINT_VERSION, ptmcore.__version__],
        "files": [_file_facts(p) for p in files],
        "lp": [hashlib.sha256(p.read_bytes()).hexdigest() for p in files if p.suffix.lower() == ".lp"],
        # Threads change how fast, not what: a batch resumed with other workers skips.
        "options": json_safe({k: v for k, v in dataclasses.asdict(item.options).items() if k != "threads"}),
        "scan": [str(item.scan), *_file_facts(item.scan), item.scan_units] if item.scan else None,
    }
    return hashlib.sha256(json.dumps(facts, sort_keys=True, default=str).encode()).hexdigest()[:32]


def is_complete(folder: Path, item: BatchItem, print_: str) -> bool:
    """Whether ``folder`` holds a finished result of ``item`` with fingerprint ``print_``.

    report.json is published last by a run, report.html last by a comparison, so a folder left
    by a killed object never passes.
    """
    try:
        report = json.loads((folder / "report.json").read_text())
    except (OSError, ValueError):
        return False
    needed = ["report.html", "mesh.ply"] + (["comparison.json"] if item.scan else [])
    return report.get("fingerprint") == print_ and all((folder / n).is_file() for n in needed)


def _row_from_folder(item: BatchItem, folder: Path, status: str, seconds: float = 0.0,
                     peak: float | None = None) -> BatchRow:
    """A row's figures, read back from the object's report.json (and comparison.json)."""
    import numpy as np
    import tifffile

    report = json.loads((folder / "report.json").read_text())
    inputs = report.get("inputs") or {}
    row = BatchRow(item.name, str(item.source), status, seconds=round(seconds, 3), peak_rss_mb=peak,
                   photographs=inputs.get("photographs"), width=inputs.get("width"), height=inputs.get("height"),
                   normals=(report.get("parameters") or {}).get("normals"), height_unit=report.get("height_unit"),
                   warnings=len(report.get("warnings") or []))
    try:
        height = tifffile.imread(folder / "height.tif")
        if np.isfinite(height).any():
            row.height_min, row.height_max = float(np.nanmin(height)), float(np.nanmax(height))
    except (OSError, ValueError):
        pass
    accuracy = (report.get("accuracy") or {}).get("normals") or {}
    row.accuracy_mean_deg = accuracy.get("mean_deg")
    if item.scan is not None and (folder / "comparison.json").is_file():
        comparison = json.loads((folder / "comparison.json").read_text())
        row.scan_rms_mm = (comparison.get("statistics_mm") or {}).get("rms")
        row.warnings += len(comparison.get("warnings") or [])
    return row


def _limit_threads(stack: ExitStack, threads: int) -> None:
    """Hold the libraries that start their own threads (BLAS, OpenMP, scipy.fft, OpenCV) to the
    worker's share of the cores, so that N workers do not start N × cores threads each."""
    import cv2
    import scipy.fft
    from threadpoolctl import threadpool_limits

    stack.enter_context(threadpool_limits(limits=threads))
    stack.enter_context(scipy.fft.set_workers(threads))
    previous = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    stack.callback(cv2.setNumThreads, previous)


def _reconstruct(item: BatchItem, folder: Path, print_: str, progress=None) -> None:
    """``reconstruct run`` of one object into ``folder``, with the comparison with its scan
    published in the same step (:func:`reconstruct.pipeline.staging.staged_output` swaps the
    whole folder in, so a batch killed at any moment leaves it old or new, never mixed)."""
    from reconstruct.pipeline import CompareOptions, run
    from reconstruct.pipeline.compare_run import ScanStep

    if item.scan is None:
        run(item.source, folder, item.options, fingerprint=print_, progress=progress)
        return
    step = ScanStep(item.scan, CompareOptions(scan_units=item.scan_units))
    result = run(item.source, folder, item.options, fingerprint=print_, then=step, progress=progress)
    step.result(result.output, result.files)


def _recover(out: Path, name: str) -> None:
    """Put back an earlier result that a batch of an earlier version, killed between its two
    renames, left as ``.replaced-<name>``, and remove its ``.running-<name>``; what a killed
    run of this version leaves, :func:`reconstruct.pipeline.staging.staged_output` handles."""
    folder, replaced = out / name, out / f".replaced-{name}"
    if replaced.exists():
        if folder.exists():
            shutil.rmtree(replaced, ignore_errors=True)
        else:
            os.rename(replaced, folder)
    shutil.rmtree(out / f".running-{name}", ignore_errors=True)


def run_object(item: BatchItem, out: str | os.PathLike, *, force: bool = False,
               threads: int = 1, token: str | None = None) -> BatchRow:
    """Reconstruct one object of a batch into ``out/<name>/``; what a Dask task runs.

    Never raises for the object's own problems: a bad capture or a failing stage is a
    ``failed`` row with the message, and an earlier result of the object stays as it was. The
    object is made in a hidden folder beside its own and swapped in when complete
    (:func:`reconstruct.pipeline.staging.staged_output`), so a batch killed at any moment leaves
    each object's folder whole (old or new); the batch's lock says no one else is writing there.
    With a ``token``, :func:`stop_objects` of that token stops the object: a ``failed`` row
    says so (the batch's process, interrupted, does not wait for it).
    """
    from ptmcore.images import allow_large_images
    from reconstruct.batch.gallery import write_thumbnails
    from reconstruct.pipeline.profiling import StageTimer
    from reconstruct.report.rendering import import_plotting

    # A worker runs objects in several threads, each drawing with matplotlib (pages, plots,
    # thumbnails): it is imported once, whole, before any of them draws. Its process is the
    # batch's, as the command's is the command's: Pillow may read what this program reads.
    import_plotting()
    allow_large_images()
    out = Path(out)
    folder = out / item.name
    print_ = fingerprint(item)
    _recover(out, item.name)
    if not force and is_complete(folder, item, print_):
        return _row_from_folder(item, folder, SKIPPED)
    if token in _STOPPED:
        return BatchRow(item.name, str(item.source), FAILED, "the batch was stopped before this object started")
    timer = StageTimer()
    t0 = time.perf_counter()
    progress = _stop_when_asked(token)
    try:
        with ExitStack() as stack:
            _limit_threads(stack, threads)
            stack.enter_context(timer.stage("object"))
            _reconstruct(item, folder, print_, progress)
    except BatchStopped as exc:
        return BatchRow(item.name, str(item.source), FAILED, str(exc), round(time.perf_counter() - t0, 3))
    except Exception as exc:  # noqa: BLE001 - a stage's bug must not stop the other objects
        message = str(exc) if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"
        return BatchRow(item.name, str(item.source), FAILED, message, round(time.perf_counter() - t0, 3))
    write_thumbnails(folder, out / "thumbnails", item.name)
    return _row_from_folder(item, folder, DONE, time.perf_counter() - t0, timer.stages["object"]["peak_rss_mb"])


def estimate_peak_mb(item: BatchItem) -> float:
    """A bound on one object's peak memory (MiB), from its photographs' size and number
    (:func:`reconstruct.pipeline.capture.peak_memory_mb`); 1 GiB when none can be read."""
    source = item.source
    if source.is_file() and source.suffix.lower() == ".ptm":
        return 400 + source.stat().st_size * 12 / 2**20
    from reconstruct.pipeline.capture import IMAGE_SUFFIXES, peak_memory_mb

    folder = source if source.is_dir() else source.parent
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    peak = peak_memory_mb(images, item.options)
    return 1024.0 if peak is None else peak


def choose_workers(items: list[BatchItem], cores: int, available_mb: float) -> int:
    """Workers for a local cluster: as many as cores and memory allow (workers × the largest
    object's estimated peak within the available memory), never more than objects."""
    peak = max(estimate_peak_mb(item) for item in items)
    return max(1, min(cores, len(items), math.floor(available_mb / peak)))

