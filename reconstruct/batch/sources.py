"""What a batch is made of: capture folders found on disk, or the rows of a manifest.

:func:`discover` takes the command line's SOURCEs: a capture folder (with an ``.lp`` file,
photometric-stereo dataset files, or photographs with spheres), an ``.lp`` or ``.ptm`` file, or a
parent folder whose immediate sub-folders and ``.ptm`` files are the captures. :func:`read_manifest`
reads a museum's spreadsheet: one row per object, a ``capture`` column, an optional ``name``,
and any ``run`` option by its long name overriding the command line for that row. Every row is
checked before anything runs.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import re
import typing
from pathlib import Path

from ptmcore.errors import InputError
from ptmcore.psdataset import is_ps_dataset
from reconstruct.batch.rows import BatchItem
from reconstruct.pipeline.capture import IMAGE_SUFFIXES
from reconstruct.pipeline.options import RunOptions, ScanUnit

__all__ = ["discover", "read_manifest", "unique_names"]

#: Manifest columns besides the run options.
_OWN_COLUMNS = ("capture", "name", "scan", "scan_units")
_TRUE, _FALSE = {"1", "true", "yes", "y"}, {"0", "false", "no", "n"}


def _is_capture(folder: Path) -> bool:
    """A folder ``run`` can take: an ``.lp`` file, dataset files, or photographs (spheres)."""
    entries = [p for p in folder.iterdir() if p.is_file()]
    return (any(p.suffix.lower() == ".lp" for p in entries) or is_ps_dataset(folder)
            or any(p.suffix.lower() in IMAGE_SUFFIXES for p in entries))


def _name_of(source: Path) -> str:
    """An object's default name: its folder's, or its file's without the suffix."""
    if source.is_file() and source.suffix.lower() == ".lp":
        return source.resolve().parent.name
    return source.stem if source.is_file() else source.resolve().name


def unique_names(names: list[str]) -> list[str]:
    """``names`` made safe as folder names and unique (``-2``, ``-3`` … for repeats)."""
    seen: dict[str, int] = {}
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
        For a source that does not exist, or a batch with no capture at all.
    """
    found: list[Path] = []
    skipped: list[tuple[Path, str]] = []
    for source in map(Path, sources):
        if not source.exists():
            raise InputError("no such capture, file or folder", source)
        if source.is_file():
            if source.suffix.lower() in (".ptm", ".lp"):
                found.append(source)
            else:
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
                    skipped.append((child, "not a capture (no .lp file, dataset files or photographs)"
                                    if child.is_dir() else "not a .ptm file"))
    if not found:
        raise InputError("no capture found in " + ", ".join(str(s) for s in sources))
    names = unique_names([_name_of(p) for p in found])
    return [BatchItem(n, p, options) for n, p in zip(names, found)], skipped


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


def read_manifest(path: str | os.PathLike, options: RunOptions) -> list[BatchItem]:
    """The objects of a manifest CSV, every row checked before anything runs.

    Parameters
    ----------
    path : path
        A CSV file with a header row: ``capture`` (a path relative to the CSV), optional
        ``name`` (the output sub-folder), ``scan``, ``scan_units``, and any
        :class:`~reconstruct.pipeline.RunOptions` field by its name (``pixel_size``, ``mask``,
        ``lp``, ``normals``, ``integrator``, ``intrinsics``, ``distance``, ``light_positions``,
        …). Empty cells keep the command line's value.
    options : RunOptions
        The command line's options, which each row overrides.

    Raises
    ------
    InputError
        Naming every bad row by its number (1 = the first row after the header) and the problem:
        an unknown column, a value the option refuses, a missing capture or scan.
    """
    path = Path(path)
    base = path.resolve().parent
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            table = list(csv.DictReader(f))
            header = list(table[0]) if table else []
    except FileNotFoundError:
        raise InputError("manifest not found", path) from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"cannot read the manifest ({exc})", path) from None
    hints = typing.get_type_hints(RunOptions)
    unknown = [c for c in header if c not in _OWN_COLUMNS and c not in hints]
    if "capture" not in header or unknown:
        known = ", ".join([*_OWN_COLUMNS, *hints])
        problem = f"unknown column(s) {', '.join(map(repr, unknown))}" if unknown else "no capture column"
        raise InputError(f"{problem}; columns are: {known}", path)
    items, errors = [], []
    for number, row in enumerate(table, 1):
        if None in row:
            errors.append(f"row {number}: more cells than columns")
            continue
        try:
            items.append(_row_item(row, base, options, hints))
        except (ValueError, InputError) as exc:
            errors.append(f"row {number}: {exc}")
    if errors:
        raise InputError("; ".join(errors), path)
    if not items:
        raise InputError("the manifest lists no object", path)
    for item, name in zip(items, unique_names([i.name for i in items])):
        item.name = name
    for k, item in enumerate(items, 1):
        item.row = k
    return items
