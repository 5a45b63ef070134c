"""What a batch is made of: capture folders found on disk, or the rows of a manifest.

:func:`discover` takes the command line's SOURCEs: a capture folder (with an ``.lp`` file,
photometric-stereo dataset files, photographs with spheres, or an RTIBuilder project's
``assembly-files/``), an ``.lp`` or ``.ptm`` file, or a
parent folder whose immediate sub-folders and ``.ptm`` files are the captures. :func:`read_manifest`
reads a museum's spreadsheet: one row per object, a ``capture`` column, an optional ``name``,
and any ``run`` option by its long name overriding the command line for that row. Every row is
checked before anything runs.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import os
import re
import typing
from pathlib import Path

from ptmcore.errors import InputError, first_few, read_input_text
from ptmcore.psdataset import is_ps_dataset
from reconstruct.batch.rows import BatchItem
from reconstruct.pipeline.capture import IMAGE_SUFFIXES
from reconstruct.pipeline.options import RunOptions, ScanUnit
from reconstruct.pipeline.projects import project_lp

__all__ = ["discover", "read_manifest", "unique_names"]

#: Manifest columns besides the run options.
_OWN_COLUMNS = ("capture", "name", "scan", "scan_units")
_TRUE, _FALSE = {"1", "true", "yes", "y"}, {"0", "false", "no", "n"}
#: The batch's own files in its output folder: an object of one of these names gets a suffix,
#: as a repeated name does, so that its folder and the file never collide.
BATCH_FILES = ("batch.csv", "batch.json", "index.html", "thumbnails")
#: The largest manifest read, in bytes: thousands of times a collection's (a row is a few
#: hundred bytes); a stray file given as the manifest is refused before it is read.
MAX_MANIFEST_BYTES = 64 * 2**20
#: A manifest cell in a message is cut to this many characters: a cell may be megabytes long.
_SHOWN_CHARS = 60


def _is_capture(folder: Path) -> bool:
    """A folder ``run`` can take: an ``.lp`` file, dataset files, photographs (spheres), or an
    RTIBuilder project (an ``.lp`` file in its ``assembly-files/``)."""
    entries = [p for p in folder.iterdir() if p.is_file()]
    return (any(p.suffix.lower() == ".lp" for p in entries) or is_ps_dataset(folder)
            or any(p.suffix.lower() in IMAGE_SUFFIXES for p in entries) or _is_project(folder))


def _is_project(folder: Path) -> bool:
    try:
        return project_lp(folder) is not None
    except InputError:
        return True  # several light files: the run names them


def _name_of(source: Path) -> str:
    """An object's default name: its folder's, or its file's without the suffix."""
    if source.is_file() and source.suffix.lower() == ".lp":
        return source.resolve().parent.name
    return source.stem if source.is_file() else source.resolve().name


def unique_names(names: list[str]) -> list[str]:
    """``names`` made safe as folder names and unique (``-2``, ``-3`` … for repeats); the
    batch's own files (:data:`BATCH_FILES`) count as taken, so ``index.html`` is ``index.html-2``."""
    seen: dict[str, int] = dict.fromkeys(BATCH_FILES, 1)
    out = []
    for name in names:
        base = re.sub(r"[^\w.\- ]+", "_", name).strip(" .") or "object"
        candidate, k = base, 1
        while candidate.lower() in seen:
            k += 1
            candidate = f"{base}-{k}"
        seen[candidate.lower()] = 1
        out.append(candidate)
    return out


def discover(sources: list[str | os.PathLike], options: RunOptions,
             ) -> tuple[list[BatchItem], list[tuple[Path, str]]]:
    """The captures named by ``sources``; returns them and what was skipped, with why.

    Raises
    ------
    InputError
        For a source that does not exist, is not a regular file or folder, or cannot be read
        (a name too long, a folder that cannot be listed), or a batch with no capture at all.
    """
    found: list[Path] = []
    skipped: list[tuple[Path, str]] = []
    for source in map(Path, sources):
        try:
            _take(source, found, skipped)
        except OSError as exc:
            raise InputError(f"cannot read it ({exc.strerror or exc})", exc.filename or source) from None
    if not found:
        why = "; ".join(f"{path.name}: {reason}" for path, reason in skipped[:5])
        more = f" and {len(skipped) - 5} more" if len(skipped) > 5 else ""
        raise InputError("no capture found in " + ", ".join(str(s) for s in sources)
                         + (f" (skipped {why}{more})" if skipped else " (it is empty)"))
    names = unique_names([_name_of(p) for p in found])
    return [BatchItem(n, p, options) for n, p in zip(names, found)], skipped


def _take(source: Path, found: list[Path], skipped: list[tuple[Path, str]]) -> None:
    """Add the captures of one SOURCE to ``found``, and what it holds that is none to ``skipped``."""
    if not source.exists():
        raise InputError("no such capture, file or folder", source)
    if source.is_file() and source.suffix.lower() in (".ptm", ".lp"):
        found.append(source)
    elif not source.is_dir():
        raise InputError("not a capture: give a folder, an .lp file or a .ptm file", source)
    elif _is_capture(source):
        found.append(source)
    else:
        for child in sorted(source.iterdir(), key=lambda p: p.name):
            if child.name.startswith("."):
                continue
            if child.is_file() and child.suffix.lower() == ".ptm":
                found.append(child)
            elif child.is_dir() and _is_capture(child):
                found.append(child)
            else:
                skipped.append((child, "not a capture (no .lp file, dataset files, photographs or "
                                       "RTIBuilder assembly-files/)" if child.is_dir() else "not a .ptm file"))


def _converter(hint: object) -> typing.Callable[[str, Path], object]:
    """How to read a manifest cell for an option of type ``hint`` (paths relative to the CSV)."""
    args = [a for a in typing.get_args(hint) if a is not type(None)] or [hint]
    if float in args:
        return lambda text, base: float(text)
    if int in args:
        return lambda text, base: int(text)
    if bool in args:
        def boolean(text: str, base: Path) -> bool:
            if text.lower() in _TRUE | _FALSE:
                return text.lower() in _TRUE
            raise ValueError(f"not yes or no: {text!r}")
        return boolean
    if Path in args:
        words = [v for a in args if typing.get_origin(a) is typing.Literal for v in typing.get_args(a)]
        return lambda text, base: text if text in words else base / text
    return lambda text, base: text


def _row_item(row: dict[str, str], base: Path, options: RunOptions, hints: dict) -> BatchItem:
    """One manifest row as an item; ValueError or InputError for a bad cell."""
    capture = (row.get("capture") or "").strip()
    if not capture:
        raise ValueError("the capture column is empty")
    source = base / capture
    if not source.exists():
        raise ValueError(f"capture not found: {source}")
    overrides = {}
    for key, text in row.items():
        text = (text or "").strip()
        if key in _OWN_COLUMNS or not text:
            continue
        try:
            overrides[key] = _converter(hints[key])(text, base)
        except ValueError as exc:
            raise ValueError(f"{key}: {exc}") from None
    scan = (row.get("scan") or "").strip()
    units = (row.get("scan_units") or "").strip() or "mm"
    if units not in typing.get_args(ScanUnit):
        raise ValueError(f"scan_units: unknown unit {units!r}; choose from {', '.join(typing.get_args(ScanUnit))}")
    item = BatchItem((row.get("name") or "").strip() or _name_of(source), source,
                     dataclasses.replace(options, **overrides), base / scan if scan else None, units)
    if item.scan is not None and not item.scan.is_file():
        raise ValueError(f"scan not found: {item.scan}")
    if item.scan is not None and item.options.pixel_size is None:
        raise ValueError("a scan needs pixel_size: a scan is compared in millimetres")
    return item


def _clip(text: str, limit: int) -> str:
    """``text`` cut to ``limit`` characters for a message (a manifest's cell may be huge)."""
    return text if len(text) <= limit else text[:limit - 1] + "…"


def _lines(text: str, path: Path) -> list[tuple[int, list[str]]]:
    """The manifest's rows as (line number, cells), the header first, blank rows left out.

    A quoted cell that goes on past its line is refused, naming the line where its quote
    opened: no manifest cell (a path, a name, an option) holds a line break, so it is a quote
    left open, which would otherwise swallow the rows after it into one cell.
    """
    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    rows = []
    while True:
        line = reader.line_num + 1
        try:
            cells = next(reader)
        except StopIteration:
            return rows
        except csv.Error as exc:
            if reader.line_num > line:
                raise InputError(f"line {line}: a quote opened on this line is never closed", path) from None
            raise InputError(f"line {line}: {exc}", path) from None
        if reader.line_num > line:
            raise InputError(f"line {line}: a quote opened on this line closes only on line {reader.line_num}; "
                             "a manifest's cells are one line each", path)
        if any(c.strip() for c in cells):
            rows.append((line, cells))


def read_manifest(path: str | os.PathLike, options: RunOptions) -> list[BatchItem]:
    """The objects of a manifest CSV, every row checked before anything runs.

    Parameters
    ----------
    path : path
        A CSV file (UTF-8, or UTF-16/32 with a byte-order mark; at most
        :data:`MAX_MANIFEST_BYTES`) with a header row: ``capture`` (a path relative to the
        CSV), optional ``name`` (the output sub-folder), ``scan``, ``scan_units``, and any
        :class:`~reconstruct.pipeline.RunOptions` field by its name (``pixel_size``, ``mask``,
        ``lp``, ``normals``, ``integrator``, ``intrinsics``, ``distance``, ``light_positions``,
        …). Empty cells keep the command line's value; blank rows are skipped.
    options : RunOptions
        The command line's options, which each row overrides.

    Raises
    ------
    InputError
        Naming bad rows by their line in the file (the spreadsheet's row number: the header is
        line 1) and the problem: an unknown column or one given twice, more cells than the
        header, a value the option refuses, a missing capture or scan; the first few, and how
        many more. Also for a quote left open, and for a manifest that is not a regular file or
        is too large.
    """
    path = Path(path)
    base = path.resolve().parent
    table = _lines(read_input_text(path, "manifest", MAX_MANIFEST_BYTES), path)
    header = [c.strip() for c in table[0][1]] if table else []
    hints = typing.get_type_hints(RunOptions)
    unknown = [_clip(repr(c), _SHOWN_CHARS) for c in header if c not in _OWN_COLUMNS and c not in hints]
    if "capture" not in header or unknown:
        known = ", ".join([*_OWN_COLUMNS, *hints])
        problem = f"unknown column(s) {first_few(unknown)}" if unknown else "no capture column"
        raise InputError(f"{problem}; columns are: {known}", path)
    twice = sorted({c for c in header if header.count(c) > 1})
    if twice:
        # Which of the two a row means cannot be known: neither is taken.
        raise InputError(f"column(s) given twice in the header: {first_few([repr(c) for c in twice])}", path)
    items, errors = [], []
    for line, cells in table[1:]:
        if any(c.strip() for c in cells[len(header):]):
            errors.append(f"line {line}: {len(cells)} cells, more than the header's {len(header)} columns")
            continue
        try:
            item = _row_item(dict(zip(header, cells)), base, options, hints)
        except (ValueError, InputError) as exc:
            errors.append(f"line {line}: {_clip(str(exc), 4 * _SHOWN_CHARS)}")
            continue
        except OSError as exc:  # a path the system refuses: a name too long, a folder unreadable
            errors.append(f"line {line}: {exc.strerror}: {_clip(str(exc.filename), _SHOWN_CHARS)}")
            continue
        item.row = line
        items.append(item)
    if errors:
        raise InputError(first_few(errors, sep="; "), path)
    if not items:
        raise InputError("the manifest lists no object", path)
    for item, name in zip(items, unique_names([i.name for i in items])):
        item.name = name
    return items
