"""One row per object of a batch: what was asked (:class:`BatchItem`) and what came of it
(:class:`BatchRow`), written as ``batch.csv`` and ``batch.json``."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
from dataclasses import dataclass
from pathlib import Path

from ptmcore.atomic import atomic_write
from reconstruct.pipeline.options import RunOptions

__all__ = ["DONE", "FAILED", "SKIPPED", "BatchItem", "BatchRow", "write_rows"]

DONE, SKIPPED, FAILED = "done", "skipped", "failed"

#: What a spreadsheet may take a cell starting with for a formula (OWASP, "CSV Injection").
_FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


@dataclass
class BatchItem:
    """One object to reconstruct.

    Attributes
    ----------
    name : str
        Its output sub-folder (unique within the batch).
    source : Path
        A capture folder, an ``.lp`` file, a ``.ptm`` file or a photometric-stereo dataset.
    options : RunOptions
        The run's options (the command line's, overridden by the manifest's row).
    scan : Path or None
        A laser scan to compare with (needs ``options.pixel_size``).
    scan_units : str
        The scan's unit.
    row : int or None
        The manifest's line it came from (the spreadsheet's row number: the header is line 1).
    """

    name: str
    source: Path
    options: RunOptions
    scan: Path | None = None
    scan_units: str = "mm"
    row: int | None = None


@dataclass
class BatchRow:
    """What became of one object (a row of ``batch.csv``).

    Attributes
    ----------
    name, source : str
        The object's output sub-folder and its capture.
    status : {"done", "skipped", "failed"}
        ``skipped``: its output was complete and its inputs and options unchanged.
    error : str
        Why it failed (empty otherwise).
    seconds : float
        Wall time of the object (0 when skipped).
    peak_rss_mb : float or None
        The worker's peak resident memory while it ran the object (sampled).
    photographs, width, height : int or None
    normals : str or None
        The normal method used.
    height_min, height_max : float or None
        The height map's range, in ``height_unit``.
    height_unit : str or None
    accuracy_mean_deg : float or None
        Mean angular error of the normals, when ground truth was found.
    scan_rms_mm : float or None
        RMS distance to the scan, when one was given.
    warnings : int
        How many warnings the run gave.
    """

    name: str
    source: str
    status: str
    error: str = ""
    seconds: float = 0.0
    peak_rss_mb: float | None = None
    photographs: int | None = None
    width: int | None = None
    height: int | None = None
    normals: str | None = None
    height_min: float | None = None
    height_max: float | None = None
    height_unit: str | None = None
    accuracy_mean_deg: float | None = None
    scan_rms_mm: float | None = None
    warnings: int = 0


def write_rows(out: str | os.PathLike, rows: list[BatchRow]) -> None:
    """Write ``batch.csv`` and ``batch.json`` into ``out`` (atomically, each)."""
    out = Path(out)
    fields = [f.name for f in dataclasses.fields(BatchRow)]
    text = io.StringIO()
    # CSV's own line ends (RFC 4180): the writer quotes a cell holding any character of them,
    # so a carriage return in an error cannot end its row early.
    writer = csv.DictWriter(text, fieldnames=fields, lineterminator="\r\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _cell(v) for k, v in dataclasses.asdict(row).items()})
    with atomic_write(out / "batch.csv", "w") as f:
        f.write(text.getvalue())
    with atomic_write(out / "batch.json", "w") as f:
        json.dump([dataclasses.asdict(r) for r in rows], f, indent=1)
        f.write("\n")


def _cell(value: object) -> object:
    """A value as ``batch.csv`` holds it: a text that a spreadsheet could take for a formula
    (a name, a path or an error starting with ``=``, ``+``, ``-``, ``@``, a tab or a carriage
    return) starts with an apostrophe, which spreadsheets show as text; numbers, negative
    heights included, stay numbers. ``batch.json`` keeps every value as it is."""
    if value is None:
        return ""
    return f"'{value}" if isinstance(value, str) and value.startswith(_FORMULA_STARTS) else value
