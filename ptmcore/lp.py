"""Light-position (``.lp``) files.

An ``.lp`` file lists one photograph per line with the unit vector towards its light::

    3
    img_000.jpg 0.5 0.0 0.866025
    C:\\capture\\img 001.jpg -0.5 0.0 0.866025
    img_002.jpg 0.0 0.5 0.866025

The first line is the count N. Each following line is a file name (which may contain spaces;
the last three fields are the vector) and x, y, z in the frame x right, y up, z towards the
camera. File names are resolved relative to the ``.lp`` file; absolute Windows paths, as
RTIBuilder writes them, are taken by their base name. The numbers are plain decimals
(``-0.5``, ``.866``, ``8.66e-1``): Python's ``float`` would also read ``0_5`` as 5 and take
``nan``, ``inf`` or other scripts' digits, none of which a light file means.

Blank lines are skipped, and so are comments: lines starting with ``#`` (RTIBuilder writes
none; other tools write a line of words, or an entry commented out). A photograph's name may
start with ``#`` too: a ``#`` line of the form of an entry (a name and three numbers,
``#1.jpg 0.1 0.2 0.97``) is a photograph when the count on the first line includes it, and a
comment when the count matches the file without it.

Some tools write light positions rather than unit vectors; they are normalised, as RTIBuilder
does. A vector that is not finite, (nearly) zero, longer than :data:`MAX_VECTOR_LENGTH`, or more
than :data:`HORIZON_CLAMP_DEG` below the horizon is refused, naming its line. One within
that of the horizon (a grazing light of a hand-held capture, whose sphere put it at −0.1°) is
raised to :data:`MIN_ELEVATION_DEG`, keeping its azimuth, and named in
:attr:`LightSet.warnings`. A photograph listed twice, or two lines with
the same direction, are allowed but reported in :attr:`LightSet.warnings`.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path, PureWindowsPath

import numpy as np

from .atomic import atomic_write
from .errors import InputError, first_few, read_input_text

#: The lowest light used: lower ones (z ≤ sin 0.5°) light nothing of a flat object and make the
#: fit ill-conditioned.
MIN_ELEVATION_DEG = 0.5

#: A light at most this far below the horizon (degrees) is raised to :data:`MIN_ELEVATION_DEG`,
#: with a warning, instead of refusing the capture: a grazing light whose direction, estimated from a reflective
#: sphere, came out a little below the horizon (a real clay relief's hand-held capture has one
#: at −0.1°; the highlight's position on a sphere is uncertain by about a degree at grazing
#: angles). Lower than that, the direction is wrong, not imprecise.
HORIZON_CLAMP_DEG = 2.0

#: Longest vector a light file may give. Light positions in millimetres or pixels stay far
#: below it; a longer vector is a typing or export error, and its square overflows.
MAX_VECTOR_LENGTH = 1e6

#: Longest light file read, and longest list of lights, intensities or light positions
#: (:mod:`ptmcore.intensity`, :mod:`ptmcore.nearlight`, :mod:`ptmcore.psdataset`): 16 MB
#: hold hundreds of thousands of lines, far more than any dome's; a larger file is not one.
MAX_TEXT_BYTES = 16 * 2**20

#: Shorter vectors give no direction (``0 0 0``, or rounding of one).
MIN_VECTOR_LENGTH = 1e-6

#: Photometric stereo needs three lights for the three components of a normal.
MIN_PHOTOGRAPHS = 3

#: Directions closer than this (in each component, after normalising) count as the same: the
#: ``.lp`` files written here and by RTIBuilder carry six decimals.
_SAME_DIRECTION = 1e-6

#: Duplicates named one by one in warnings; the rest are counted.
_SHOWN = 3

#: A plain decimal number: sign, digits with a decimal point, exponent, in ASCII.
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


@dataclass(frozen=True)
class LightSet:
    """Photographs and the directions towards their lights.

    Attributes
    ----------
    paths : list of Path
        Image files, resolved to where they are on this machine.
    directions : ndarray, shape (N, 3), float64
        Unit vectors towards the lights (x right, y up, z towards the camera).
    source : Path or None
        The ``.lp`` file they came from.
    warnings : tuple of str
        What a user should know about the file that does not stop a run: a light raised from
        just below the horizon, a photograph listed twice, or two photographs with the same
        light direction, naming the lines.
    names : tuple of str
        The photographs' names as the file writes them (an RTIBuilder project's are absolute
        paths on the machine that built it); empty when not read from a file.
    """

    paths: list[Path]
    directions: np.ndarray
    source: Path | None = None
    warnings: tuple[str, ...] = ()
    names: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.paths)


def decimal_number(text: str) -> float:
    """The value of a plain decimal number (``-0.5``, ``.866``, ``8.66e-1``, ``1e400`` is inf).

    Raises
    ------
    ValueError
        For anything else that ``float`` would take: ``0_5``, ``nan``, ``inf``, ``0x1p3``,
        other scripts' digits, surrounding spaces.
    """
    if not _DECIMAL.fullmatch(text):
        raise ValueError(f"not a decimal number: {text!r}")
    return float(text)


def _entry_form(line: str) -> bool:
    """Whether ``line`` reads as ``name x y z``."""
    fields = line.split()
    return len(fields) >= 4 and all(_DECIMAL.fullmatch(f) for f in fields[-3:])


def _resolve(name: str, base: Path) -> Path:
    # A path written on Windows (``C:\\x\\img.jpg`` or ``\\\\server\\share\\img.jpg``) cannot
    # mean anything here; the photograph is expected beside the .lp file.
    if PureWindowsPath(name).drive or "\\" in name:
        return base / PureWindowsPath(name).name
    p = Path(name)
    if p.is_absolute() and not _exists(p):
        return base / p.name
    return p if p.is_absolute() else base / p


def _exists(p: Path) -> bool:
    # A name too long for the file system cannot be there (Path.exists raises for it).
    try:
        return p.exists()
    except OSError:
        return False


def unit_directions(
    vectors: np.ndarray, lines: list[int], path: str | os.PathLike, labels: list[str] | None = None,
    *, raised: list[str] | None = None,
) -> np.ndarray:
    """Unit light directions from the vectors of a light file, each checked.

    Parameters
    ----------
    vectors : ndarray, shape (N, 3)
        The vectors as read (unit vectors, or light positions to be normalised).
    lines : list of int
        The 1-based line number of each vector, for messages.
    path : str or PathLike
        The file, for messages.
    labels : list of str, optional
        What each vector belongs to (a photograph's name); default "light K".
    raised : list of str, optional
        Receives one warning per light raised from just below the horizon to
        :data:`MIN_ELEVATION_DEG` (see :data:`HORIZON_CLAMP_DEG`).

    Returns
    -------
    ndarray, shape (N, 3), float64
        Unit vectors.

    Raises
    ------
    InputError
        At the first vector (in line order) that is not finite, is (nearly) zero or longer
        than :data:`MAX_VECTOR_LENGTH`, or points more than :data:`HORIZON_CLAMP_DEG` below
        the horizon.
    """
    v = np.asarray(vectors, dtype=np.float64).reshape(-1, 3)
    finite = np.isfinite(v).all(axis=1)
    safe = np.where(finite[:, None], v, 0.0)
    # Scaled by the largest component first, so that the length of a 1e200-long vector does
    # not overflow (it would normalise to zero, and be called "below the horizon").
    big = np.abs(safe).max(axis=1)
    scaled = safe / np.where(big > 0, big, 1.0)[:, None]
    norm = np.linalg.norm(scaled, axis=1)
    with np.errstate(over="ignore"):
        length = big * norm
    unit = scaled / np.where(norm > 0, norm, 1.0)[:, None]
    lowest = math.sin(math.radians(-HORIZON_CLAMP_DEG))
    low = unit[:, 2] <= lowest
    bad = ~finite | (length < MIN_VECTOR_LENGTH) | (length > MAX_VECTOR_LENGTH) | low
    if not bad.any():
        return _raise_grazing(unit, lines, labels, raised)
    k = int(np.argmax(bad))
    what = _label(labels, k)
    shown = " ".join(f"{x:g}" for x in v[k])
    if not finite[k]:
        problem = f"{what} ({shown}) is not finite"
    elif length[k] < MIN_VECTOR_LENGTH:
        problem = f"{what} ({shown}) has zero length"
    elif length[k] > MAX_VECTOR_LENGTH:
        problem = (f"{what} ({shown}) is not a direction of sensible length: its length is "
                   f"{length[k]:.3g} (expected a unit vector, or a light position within {MAX_VECTOR_LENGTH:g})")
    else:
        elev = math.degrees(math.asin(float(np.clip(unit[k, 2], -1.0, 1.0))))
        problem = (f"{what} is below the horizon (elevation {elev:.1f}°, lower than the "
                   f"−{HORIZON_CLAMP_DEG:g}° taken as a grazing light; "
                   "z must point towards the camera)")
    raise InputError(f"line {lines[k]}: {problem}", path)


def _label(labels: list[str] | None, k: int) -> str:
    return f"light direction of {labels[k]!r}" if labels is not None else f"light direction {k + 1}"


def _raise_grazing(unit: np.ndarray, lines: list[int], labels: list[str] | None,
                   raised: list[str] | None) -> np.ndarray:
    """``unit`` with the lights lower than :data:`MIN_ELEVATION_DEG` raised to it, azimuth kept."""
    z_min = math.sin(math.radians(MIN_ELEVATION_DEG))
    low = np.flatnonzero(unit[:, 2] <= z_min)
    if len(low) == 0:
        return unit
    out = unit.copy()
    xy = out[low, :2]
    radius = np.linalg.norm(xy, axis=1, keepdims=True)
    # Nudged above the limit so that the raised light passes the same test everywhere else.
    z = math.sin(math.radians(MIN_ELEVATION_DEG) + 1e-9)
    out[low, :2] = xy / radius * math.sqrt(1.0 - z * z)
    out[low, 2] = z
    if raised is not None:
        for k in low:
            elev = math.degrees(math.asin(float(np.clip(unit[k, 2], -1.0, 1.0))))
            raised.append(f"line {lines[k]}: {_label(labels, k)} is at {elev:.2f}° elevation, at or just "
                          f"below the horizon; it is used as a grazing light at {MIN_ELEVATION_DEG:g}°")
    return out


def read_lp(path: str | os.PathLike) -> LightSet:
    """Read an ``.lp`` light file.

    Parameters
    ----------
    path : str or PathLike
        The ``.lp`` file.

    Returns
    -------
    LightSet
        Image paths resolved relative to the file's folder, unit light directions, and
        warnings about duplicate entries.

    Raises
    ------
    InputError
        If the file is missing, unreadable, not a regular file, larger than
        :data:`MAX_TEXT_BYTES` or UTF-16 without a byte-order mark, the count does not match
        the lines, a line does not parse, has no file name or a NUL byte in it, a vector is
        (nearly) zero, not finite, absurdly long, or more than :data:`HORIZON_CLAMP_DEG` below
        the horizon, or the file lists
        fewer than :data:`MIN_PHOTOGRAPHS`.
    """
    path = Path(path)
    text = read_input_text(path, "light file", max_bytes=MAX_TEXT_BYTES)
    if text.count("\0") * 3 >= len(text) > 0:
        # NULs between the characters: UTF-16 (Notepad's "Unicode") without the byte-order mark
        # that would tell it.
        raise InputError("the light file is UTF-16 text without a byte-order mark; save it as UTF-8", path)
    lines = [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines())]
    lines = [(no, ln) for no, ln in lines if ln]
    # A photograph cannot come before the count: a '#' line there is a comment.
    head = next((k for k, (_, ln) in enumerate(lines) if not ln.startswith("#")), None)
    if head is None:
        raise InputError("light file is empty", path)
    no, first = lines[head]
    if not re.fullmatch(r"[0-9]+", first.split()[0]):
        raise InputError(f"line {no}: expected the number of photographs, got {first[:40]!r}", path)
    count = int(first.split()[0])
    entries = _entries(lines[head + 1:], count, path)

    base = path.parent
    names: list[str] = []
    paths: list[Path] = []
    vectors = np.empty((count, 3), dtype=np.float64)
    for k, (no, line) in enumerate(entries):
        fields = line.split()
        if len(fields) < 4:
            raise InputError(f"line {no}: expected 'filename x y z', got {line[:60]!r}", path)
        try:
            vectors[k] = [decimal_number(f) for f in fields[-3:]]
        except ValueError:
            raise InputError(f"line {no}: light direction is not three numbers (plain decimals, as 0.5 or "
                             f"-8.66e-1): {line[:60]!r}", path) from None
        # Names may contain spaces: the name is everything before the last three fields.
        name = line.rsplit(maxsplit=3)[0]
        if "\0" in name:
            raise InputError(f"line {no}: the photograph's name holds a NUL byte, which no file name can", path)
        resolved = _resolve(name, base)
        if not resolved.name:
            raise InputError(f"line {no}: no file name in {line[:60]!r}", path)
        names.append(name)
        paths.append(resolved)
    numbers = [no for no, _ in entries]
    raised: list[str] = []
    directions = unit_directions(vectors, numbers, path, names, raised=raised)
    if count < MIN_PHOTOGRAPHS:
        raise InputError(
            f"lists {count} photograph{'s' if count != 1 else ''}; at least {MIN_PHOTOGRAPHS} "
            "are needed to recover normals",
            path,
        )
    return LightSet(paths=paths, directions=directions, source=path,
                    warnings=tuple(raised) + duplicate_warnings(paths, directions, numbers), names=tuple(names))


def _entries(lines: list[tuple[int, str]], count: int, path: Path) -> list[tuple[int, str]]:
    """The numbered lines after the count that list photographs: every line not starting with
    ``#``, and the ``#`` lines of the form of an entry when ``count`` includes them (a
    photograph named ``#1.jpg``); otherwise those are comments (an entry commented out)."""
    plain = [(no, ln) for no, ln in lines if not ln.startswith("#")]
    named = [(no, ln) for no, ln in lines if not ln.startswith("#") or _entry_form(ln)]
    for entries in (named, plain):
        if len(entries) == count:
            return entries
    besides = f" ({len(plain)} besides the lines starting with '#')" if len(plain) != len(named) else ""
    raise InputError(f"declares {count} photographs but lists {len(named)}{besides}", path)


def duplicate_warnings(paths: list[Path], directions: np.ndarray, lines: list[int]) -> tuple[str, ...]:
    """Warnings for a photograph listed on several lines and for lines sharing one direction.

    Neither stops a run (repeated exposures under one light are legitimate), but a photograph
    given two different directions is surely a mistake, and a repeated line usually is one:
    both weigh that light twice in every fit.
    """
    out: list[str] = []
    by_path: dict[Path, list[int]] = {}
    for k, p in enumerate(paths):
        by_path.setdefault(p, []).append(k)
    twice = [ks for ks in by_path.values() if len(ks) > 1]
    for ks in twice[:_SHOWN]:
        same = np.ptp(directions[ks], axis=0).max() <= _SAME_DIRECTION
        how = "with the same direction" if same else "with different directions"
        out.append(f"{_line_list([lines[k] for k in ks])} list the same photograph {paths[ks[0]].name} {how}")
    if len(twice) > _SHOWN:
        out.append(f"{len(twice) - _SHOWN} more photograph(s) are listed more than once")
    # Lines that repeat one photograph were reported above; here, different photographs.
    first = {ks[0] for ks in by_path.values()}
    keep = np.array(sorted(first))
    key = np.round(directions[keep] / _SAME_DIRECTION).astype(np.int64)
    _, group, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    shared = [keep[group.ravel() == g] for g in np.flatnonzero(counts > 1)]
    shared.sort(key=lambda ks: ks[0])
    for ks in shared[:_SHOWN]:
        out.append(f"{_line_list([lines[k] for k in ks])} give the same light direction "
                   f"({first_few([paths[k].name for k in ks])})")
    if len(shared) > _SHOWN:
        out.append(f"{len(shared) - _SHOWN} more light direction(s) are shared by several photographs")
    return tuple(out)


def _line_list(numbers: list[int]) -> str:
    """``lines 3 and 7`` or ``lines 3, 7 and 9``."""
    shown = [str(n) for n in numbers]
    return f"lines {', '.join(shown[:-1])} and {shown[-1]}"


def as_directions(directions: np.ndarray, count: int, dtype: type = np.float64) -> np.ndarray:
    """Check that ``directions`` holds one (x, y, z) light direction per photograph.

    Returns
    -------
    ndarray, shape (count, 3)
        The directions as ``dtype``.
    """
    d = np.asarray(directions, dtype=dtype)
    if d.shape != (count, 3):
        raise ValueError(f"expected {count} light directions, got array of shape {d.shape}")
    return d


def write_lp(path: str | os.PathLike, names: list[str], directions: np.ndarray) -> None:
    """Write an ``.lp`` light file.

    Parameters
    ----------
    path : str or PathLike
        Destination.
    names : list of str
        File names as they should appear (relative to the file's folder).
    directions : ndarray, shape (N, 3)
        Unit vectors towards the lights.
    """
    directions = np.asarray(directions, dtype=np.float64)
    if directions.shape != (len(names), 3):
        raise ValueError("directions must have shape (len(names), 3)")
    lines = [str(len(names))]
    lines += [f"{n} {x:.6f} {y:.6f} {z:.6f}" for n, (x, y, z) in zip(names, directions)]
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines) + "\n")
