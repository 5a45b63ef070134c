"""Light-position (``.lp``) files.

An ``.lp`` file lists one photograph per line with the unit vector towards its light::

    3
    img_000.jpg 0.5 0.0 0.866025
    C:\\capture\\img 001.jpg -0.5 0.0 0.866025
    img_002.jpg 0.0 0.5 0.866025

The first line is the count N. Each following line is a file name (which may contain spaces;
the last three fields are the vector) and x, y, z in the frame x right, y up, z towards the
camera. File names are resolved relative to the ``.lp`` file; absolute Windows paths, as
RTIBuilder writes them, are taken by their base name.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path, PureWindowsPath

import numpy as np

from .atomic import atomic_write
from .errors import InputError, read_input_text

#: Lights lower than this above the horizon (z ≤ sin 0.5°) are rejected: they light nothing
#: of a flat object and make the fit ill-conditioned.
MIN_ELEVATION_DEG = 0.5


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
    """

    paths: list[Path]
    directions: np.ndarray
    source: Path | None = None

    def __len__(self) -> int:
        return len(self.paths)


def _resolve(name: str, base: Path) -> Path:
    # A path written on Windows (``C:\\x\\img.jpg`` or ``\\\\server\\share\\img.jpg``) cannot
    # mean anything here; the photograph is expected beside the .lp file.
    if PureWindowsPath(name).drive or "\\" in name:
        return base / PureWindowsPath(name).name
    p = Path(name)
    if p.is_absolute() and not p.exists():
        return base / p.name
    return p if p.is_absolute() else base / p


def read_lp(path: str | os.PathLike) -> LightSet:
    """Read an ``.lp`` light file.

    Parameters
    ----------
    path : str or PathLike
        The ``.lp`` file.

    Returns
    -------
    LightSet
        Image paths resolved relative to the file's folder and unit light directions.

    Raises
    ------
    InputError
        If the file is missing or unreadable, the count does not match the lines, a line does
        not parse, a vector is zero, not finite, or at or below the horizon.
    """
    path = Path(path)
    text = read_input_text(path, "light file")
    lines = [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines())]
    lines = [(no, ln) for no, ln in lines if ln and not ln.startswith("#")]
    if not lines:
        raise InputError("light file is empty", path)
    try:
        count = int(lines[0][1].split()[0])
    except (ValueError, IndexError):
        raise InputError(
            f"line {lines[0][0]}: expected the number of photographs, got {lines[0][1][:40]!r}", path
        ) from None
    entries = lines[1:]
    if count != len(entries):
        raise InputError(f"declares {count} photographs but lists {len(entries)}", path)

    base = path.parent
    paths: list[Path] = []
    dirs = np.empty((count, 3), dtype=np.float64)
    for k, (no, line) in enumerate(entries):
        fields = line.split()
        if len(fields) < 4:
            raise InputError(f"line {no}: expected 'filename x y z', got {line[:60]!r}", path)
        try:
            vec = [float(f) for f in fields[-3:]]
        except ValueError:
            raise InputError(f"line {no}: light direction is not three numbers: {line[:60]!r}", path) from None
        # Names may contain spaces: the name is everything before the last three fields.
        name = line.rsplit(maxsplit=3)[0]
        v = np.asarray(vec)
        norm = float(np.linalg.norm(v))
        if not np.all(np.isfinite(v)):
            raise InputError(f"line {no}: light direction is not finite", path)
        if norm < 1e-6:
            raise InputError(f"line {no}: light direction of {name!r} has zero length", path)
        # Some tools write light positions rather than unit vectors; RTIBuilder normalises
        # them too.
        v = v / norm
        if v[2] <= math.sin(math.radians(MIN_ELEVATION_DEG)):
            elev = math.degrees(math.asin(max(-1.0, min(1.0, v[2]))))
            raise InputError(
                f"line {no}: light of {name!r} is at or below the horizon (elevation {elev:.1f}°; "
                "z must point towards the camera)",
                path,
            )
        dirs[k] = v
        paths.append(_resolve(name, base))
    return LightSet(paths=paths, directions=dirs, source=path)


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
