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
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

from ptmcore.errors import InputError, open_input_file, read_input_text
from reconstruct.batch.rows import DONE, FAILED, SKIPPED, BatchItem, BatchRow
from reconstruct.pipeline.report import json_safe

__all__ = ["BatchStopped", "already_done", "choose_workers", "describe_failure", "estimate_peak_mb", "fingerprint", "is_complete",
           "run_object", "stop_objects"]

#: Fingerprint format; a new one makes every object run again.
_FINGERPRINT_VERSION = 2

#: A failure's message in a row at most, in characters: a library's message may be pages long.
_MESSAGE_CHARS = 500

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


class _Watch:
    """The progress callback of an object's run: it remembers the stage reported last (a
    failure's message names it) and, in a batch stopped by :func:`stop_objects` (its
    ``token``), raises :class:`BatchStopped`."""

    def __init__(self, token: str | None) -> None:
        self.token = token
        self.stage: str | None = None

    def __call__(self, stage: str, done: int, total: int) -> None:
        self.stage = stage
        if self.token is not None and self.token in _STOPPED:
            raise BatchStopped(f"the batch was stopped during the {stage} stage")


def _regular_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file()) if folder.is_dir() else []


def _run_inputs(item: BatchItem) -> tuple[set[Path], set[Path]]:
    """The files an object's run reads, as (photographs, the others), as far as they can be found.

    The photographs: those of its folder, those its ``.lp`` files list (wherever they are) and
    a ``.ptm`` source. The others: every other file of its folder (``.lp``, dataset files), the
    ``--lp`` given, the ``light_positions.csv`` beside each ``.lp`` (or the file given), the
    mask, the intensities, the ambient frame, the flat-field board's files, the ground truth's files (given, or ``ground_truth/`` of the
    capture) and the scan. A file that does not exist is listed too: its appearing matters.
    """
    from ptmcore.lp import read_lp
    from reconstruct.pipeline.capture import IMAGE_SUFFIXES
    from reconstruct.pipeline.projects import locate_photographs, project_lp

    source, opt = item.source, item.options
    if source.suffix.lower() == ".ptm" and not source.is_dir():
        photographs, others = {source}, set()
    else:
        folder = source if source.is_dir() else source.parent
        files = _regular_files(folder)
        photographs = {p for p in files if p.suffix.lower() in IMAGE_SUFFIXES}
        others = set(files) - photographs
        lps = [opt.lp] if opt.lp is not None else [p for p in files if p.suffix.lower() == ".lp"]
        try:
            lps = lps or [p for p in [project_lp(folder)] if p is not None]  # an RTIBuilder project
        except InputError:
            pass  # several: the run fails on them, and names them
        for lp in lps:
            others.add(lp)
            if opt.light_positions == "auto":
                others.add(lp.parent / "light_positions.csv")
            try:
                photographs.update(locate_photographs(read_lp(lp), source).paths)
            except InputError:
                pass  # the run fails on it, and names it; its content is in the fingerprint
    truth = opt.ground_truth or (source if source.is_dir() else source.parent) / "ground_truth"
    others.update(_regular_files(truth))
    others.update(Path(p) for p in (opt.mask, opt.light_positions, item.scan) if isinstance(p, Path))
    if opt.intensities not in (None, "estimate"):
        others.add(Path(opt.intensities))
    if opt.ambient is not None:  # a photograph, but an input like the mask: its content counts
        others.add(opt.ambient)
    if opt.flat_field is not None:  # the board's photographs and .lp, by size and time as photographs are
        photographs.update(_regular_files(opt.flat_field))
    return photographs, others - photographs


def _photograph_facts(path: Path) -> list:
    """A photograph's (or a PTM's) part of a fingerprint: its size and modification time.

    Hashing them would read every photograph of the collection again at each resume, as
    long as decoding them; a photograph edited, exported again or replaced gets a new
    modification time (a copy keeps it only when asked to, ``cp -p``).
    """
    try:
        stat = path.stat()
    except OSError as exc:
        return [exc.strerror]
    return [stat.st_size, stat.st_mtime_ns]


def _content_facts(path: Path) -> str:
    """Any other input's part of a fingerprint: the SHA-256 of its content (these files are
    small beside the photographs, and a mask or light file is often rewritten in place)."""
    try:
        with open_input_file(path, "file") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()
    except (InputError, OSError) as exc:
        # Missing or unreadable: the run fails on it and names it; once it is put right,
        # the fingerprint changes.
        return str(exc)


def fingerprint(item: BatchItem) -> str:
    """A hash of what an object's result depends on: the content of every input its run reads
    besides the photographs (``.lp`` files wherever they are, mask, light positions,
    intensities, ground truth, scan and the folder's other files), the photographs' names,
    sizes and modification times (:func:`_photograph_facts`), and its options.

    A changed photograph, light file, mask, scan, ground truth or option gives another
    fingerprint, so a batch run again redoes that object and skips the others. Files of the
    capture's folder are named by their name alone, so a collection moved elsewhere with its
    files' times still skips.
    """
    import ptmcore

    photographs, others = _run_inputs(item)
    folder = item.source if item.source.is_dir() else item.source.parent

    def key(path: Path) -> str:
        return path.name if path.parent == folder else str(path)

    facts = {
        "version": [_FINGERPRINT_VERSION, ptmcore.__version__],
        "photographs": {key(p): _photograph_facts(p) for p in photographs},
        "inputs": {key(p): _content_facts(p) for p in others},
        # Threads change how fast, not what: a batch resumed with other workers skips.
        "options": json_safe({k: v for k, v in dataclasses.asdict(item.options).items() if k != "threads"}),
        "scan_units": item.scan_units if item.scan else None,
    }
    return hashlib.sha256(json.dumps(facts, sort_keys=True, default=str).encode()).hexdigest()[:32]


def describe_failure(exc: BaseException, stage: str | None = None) -> str:
    """What a failed object's row says of ``exc``, raised during ``stage`` (when known).

    An :class:`InputError` says it all. Running out of memory says so, and what to do. Any
    other exception is its type and message, on one line of at most :data:`_MESSAGE_CHARS`
    characters (as ``batch.csv`` and the summary show it); one without a message
    (``KeyError()``, an ``assert``) gets its type's meaning in words, from the first line of its
    documentation.
    """
    if isinstance(exc, InputError):
        return str(exc)
    during = f" during the {stage} stage" if stage else ""
    text = " ".join(str(exc).split())
    if len(text) > _MESSAGE_CHARS:
        text = text[:_MESSAGE_CHARS - 1] + "…"
    if isinstance(exc, MemoryError):
        return (f"ran out of memory{during}" + (f" ({text})" if text else "")
                + ": run fewer objects at once (--workers) or give --memory-limit")
    if not text:
        doc = next((c.__doc__.strip() for c in type(exc).__mro__ if c.__doc__ and c.__doc__.strip()), "")
        text = doc.splitlines()[0].rstrip(".").lower() if doc else "no message"
    return f"{type(exc).__name__}{during}: {text}"


def _read_json(path: Path) -> dict:
    """An output's JSON object (report.json, comparison.json); empty when it is missing, not
    a regular file (it is read without blocking) or not a JSON object."""
    try:
        value = json.loads(read_input_text(path, "JSON file"))
    except (InputError, ValueError):
        return {}
    return value if isinstance(value, dict) else {}


def is_complete(folder: Path, item: BatchItem, print_: str) -> bool:
    """Whether ``folder`` holds a finished result of ``item`` with fingerprint ``print_``.

    report.json is published last by a run, report.html last by a comparison, so a folder left
    by a killed object never passes.
    """
    report = _read_json(folder / "report.json")
    needed = ["report.html", "mesh.ply"] + (["comparison.json"] if item.scan else [])
    return report.get("fingerprint") == print_ and all((folder / n).is_file() for n in needed)


def _row_from_folder(item: BatchItem, folder: Path, status: str, seconds: float = 0.0,
                     peak: float | None = None) -> BatchRow:
    """A row's figures, read back from the object's report.json (and comparison.json)."""
    import numpy as np
    import tifffile

    report = _read_json(folder / "report.json")
    inputs = report.get("inputs") or {}
    row = BatchRow(item.name, str(item.source), status, seconds=round(seconds, 3), peak_rss_mb=peak,
                   photographs=inputs.get("photographs"), width=inputs.get("width"), height=inputs.get("height"),
                   normals=(report.get("parameters") or {}).get("normals"), height_unit=report.get("height_unit"),
                   warnings=len(report.get("warnings") or []))
    try:
        height = tifffile.imread(folder / "height.tif") if (folder / "height.tif").is_file() else np.empty(0)
        if np.isfinite(height).any():
            row.height_min, row.height_max = float(np.nanmin(height)), float(np.nanmax(height))
    except (OSError, ValueError):
        pass
    accuracy = (report.get("accuracy") or {}).get("normals") or {}
    row.accuracy_mean_deg = accuracy.get("mean_deg")
    if item.scan is not None:
        comparison = _read_json(folder / "comparison.json")
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


def already_done(item: BatchItem, out: Path) -> BatchRow | None:
    """The ``skipped`` row of an object whose folder in ``out`` is complete and made from the
    same inputs and options (:func:`fingerprint`, :func:`is_complete`), else None: what a
    batch decides before starting any worker. Any problem reading the inputs is left to
    :func:`run_object`, which reports it."""
    try:
        print_ = fingerprint(item)
        _recover(out, item.name)
        if is_complete(out / item.name, item, print_):
            return _row_from_folder(item, out / item.name, SKIPPED)
    except Exception:  # noqa: BLE001, S110 - run_object meets it again and says what it is
        pass
    return None


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
    try:
        print_ = fingerprint(item)
    except Exception as exc:  # noqa: BLE001 - an unreadable capture folder fails this object alone
        return BatchRow(item.name, str(item.source), FAILED, describe_failure(exc))
    _recover(out, item.name)
    if not force and is_complete(folder, item, print_):
        return _row_from_folder(item, folder, SKIPPED)
    if token in _STOPPED:
        return BatchRow(item.name, str(item.source), FAILED, "the batch was stopped before this object started")
    timer = StageTimer()
    t0 = time.perf_counter()
    watch = _Watch(token)
    try:
        with ExitStack() as stack:
            _limit_threads(stack, threads)
            stack.enter_context(timer.stage("object"))
            _reconstruct(item, folder, print_, watch)
    except BatchStopped as exc:
        return BatchRow(item.name, str(item.source), FAILED, str(exc), round(time.perf_counter() - t0, 3))
    except Exception as exc:  # noqa: BLE001 - a stage's bug must not stop the other objects
        return BatchRow(item.name, str(item.source), FAILED, describe_failure(exc, watch.stage),
                        round(time.perf_counter() - t0, 3))
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


def choose_workers(items: list[BatchItem], cores: int, available_mb: float, wanted: int | None = None,
                   echo: Callable[[str], None] = lambda line: None) -> int:
    """Workers for a local cluster: as many as cores and memory allow (workers × the largest
    object's estimated peak within the available memory), never more than objects.

    ``wanted`` (``--workers``) is taken within the same bounds: more workers than the CPUs
    would only crowd them, and more than the memory holds would be killed for memory; ``echo``
    is told when it is cut, and why.
    """
    peak = max(estimate_peak_mb(item) for item in items)
    allowed = max(1, min(cores, math.floor(available_mb / peak)))
    if wanted is not None and wanted > allowed:
        echo(f"warning: {wanted} workers are more than this machine allows: {cores} CPU(s), and "
             f"{available_mb:,.0f} MB of memory for objects of up to {peak:,.0f} MB each; using {allowed}")
    return min(wanted or allowed, allowed, len(items))
