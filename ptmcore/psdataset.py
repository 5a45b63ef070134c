"""A photometric-stereo dataset folder (the DiLiGenT benchmark's layout) as input.

The folder holds::

    filenames.txt            one image file name per line (001.png, 002.png, ...)
    light_directions.txt     one "x y z" per image: unit vector towards the light
    light_intensities.txt    one "r g b" per image: the light's strength per channel
    mask.png                 optional: the object (non-zero)
    Normal_gt.png            optional: ground-truth normals, 16-bit, value = (n + 1) / 2 · 65535
    001.png ...              16-bit linear RGB photographs

Directions and normals are in the project's frame (x right, y up, z towards the camera), the
frame of ``.lp`` files; the normal map is OpenGL-style (R = x, G = y, B = z). That is also
DiLiGenT's own frame. Each photograph is divided, per channel, by its light's intensity before
it is reduced to luminance, so the stack is what lights of equal strength would have given.

If ``Normal_gt.png`` is missing but ``Normal_gt.mat`` (DiLiGenT's float normals, variable
``Normal_gt``) is present, that is read instead. If ``filenames.txt`` is missing, the images
are taken to be ``001.png`` … in the order of ``light_directions.txt``, as in DiLiGenT's
multi-view data, provided they all exist.
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PureWindowsPath

import numpy as np

from .errors import InputError, read_input_file, read_input_text
from .images import ImageStack, load_stack, read_image
from .intensity import check_positive, read_numeric_rows
from .lp import MAX_TEXT_BYTES, MIN_PHOTOGRAPHS, LightSet, unit_directions

FILENAMES = "filenames.txt"
DIRECTIONS = "light_directions.txt"
INTENSITIES = "light_intensities.txt"
MASK = "mask.png"
NORMALS_PNG = "Normal_gt.png"
NORMALS_MAT = "Normal_gt.mat"

#: A decoded ground-truth pixel whose length is further than this from 1 is not a normal (the
#: background of a normal map is stored as black, grey or white); 8-bit quantisation moves
#: the length by less than 0.01.
_UNIT_TOLERANCE = 0.1

#: Bytes per pixel a ``Normal_gt.mat`` may hold: its normals as doubles (24), and as much
#: again beside them; and room for its headers.
_MAT_BYTES_PER_PIXEL = 48
_MAT_HEADERS = 2**20


@dataclass
class PSDataset:
    """A photometric-stereo dataset, read by :func:`read_ps_dataset`.

    Attributes
    ----------
    folder : Path
        The dataset folder.
    lights : LightSet
        Image paths and unit light directions (x right, y up, z towards the camera);
        ``lights.source`` is ``light_directions.txt``.
    intensities : ndarray, shape (N, 3), float64
        Each light's strength per channel (R, G, B), as listed.
    intensity_scale : float
        The stack holds each photograph × ``intensity_scale`` / its intensities (the photographs
        as stored, and 1, with ``divide_intensities=False``). It is 1 unless
        some intensity is below 1, when it is the smallest intensity: dividing by a value
        below 1 would push bright samples past the stored range. One global factor changes
        only the albedo's scale.
    mask : ndarray, shape (H, W), bool, or None
        The object, from ``mask.png``.
    ground_truth_normals : ndarray, shape (H, W, 3), float32, or None
        Unit normals from ``Normal_gt.png`` (or ``Normal_gt.mat``); (0, 0, 0) where the file
        holds no unit vector (its background), NaN where the ``.mat`` file holds NaN.
    stack : ImageStack
        The photographs, intensities divided out, as luminance and chroma.
    """

    folder: Path
    lights: LightSet
    intensities: np.ndarray
    intensity_scale: float
    mask: np.ndarray | None
    ground_truth_normals: np.ndarray | None
    stack: ImageStack

    def __len__(self) -> int:
        return len(self.lights)


def is_ps_dataset(folder: str | os.PathLike) -> bool:
    """Whether ``folder`` looks like a photometric-stereo dataset folder.

    True for a folder holding ``light_directions.txt`` together with ``filenames.txt`` or
    ``light_intensities.txt``; :func:`read_ps_dataset` then says what else is missing or wrong.
    """
    folder = Path(folder)
    try:
        return (folder / DIRECTIONS).is_file() and (
            (folder / FILENAMES).is_file() or (folder / INTENSITIES).is_file()
        )
    except OSError:
        return False


def _read_filenames(folder: Path, count: int) -> list[Path]:
    """Image paths from ``filenames.txt``, or the numbered images when it is missing."""
    path = folder / FILENAMES
    if not os.path.lexists(path):
        numbered = [folder / f"{k:03d}.png" for k in range(1, count + 1)]
        if count and all(p.is_file() for p in numbered):
            return numbered
        raise InputError(
            f"file list not found (and the images are not 001.png … {count:03d}.png)", path
        )
    text = read_input_text(path, "file list", max_bytes=MAX_TEXT_BYTES)
    paths = []
    for line in text.splitlines():
        name = line.strip()
        if not name or name.startswith("#"):
            continue
        # A name written on Windows means the file beside the list.
        if "\\" in name or PureWindowsPath(name).drive:
            name = PureWindowsPath(name).name
        p = Path(name)
        paths.append(p if p.is_absolute() else folder / p)
    if not paths:
        raise InputError("file list is empty", path)
    return paths


def _read_directions(path: Path, raised: list[str]) -> np.ndarray:
    """Unit light directions from ``light_directions.txt``, checked to be above the horizon
    (those just below it raised, a warning for each appended to ``raised``)."""
    values, lines = read_numeric_rows(path, "light direction file", (3,))
    # Some tools write light positions rather than unit vectors; only the direction matters.
    return unit_directions(values, lines, path, raised=raised)


def _read_intensities(path: Path, count: int) -> np.ndarray:
    """``(N, 3)`` positive intensities; a single value per line is taken for all channels."""
    values, lines = read_numeric_rows(path, "light intensity file", (1, 3))
    check_positive(values, lines, path, "light intensity")
    if len(values) != count:
        raise InputError(
            f"lists {len(values)} intensities but {DIRECTIONS} lists {count} lights", path
        )
    return np.repeat(values, 3, axis=1) if values.shape[1] == 1 else values


def _read_mask(path: Path, shape: tuple[int, int]) -> np.ndarray:
    img = read_image(path)
    if img.shape[:2] != shape:
        raise InputError(
            f"mask is {img.shape[1]}×{img.shape[0]} but the images are {shape[1]}×{shape[0]}", path
        )
    if img.ndim == 3:
        img = img.max(axis=2)
    top = float(img.max())
    if top <= 0:
        raise InputError("mask is empty (all black)", path)
    # Half the mask's own maximum: 0/255, 0/65535 and 0/1 masks alike, and antialiased edges
    # split as DiLiGenT's evaluation (im2bw at 0.5) splits them.
    return img > 0.5 * top


def _decode_normal_png(path: Path, shape: tuple[int, int]) -> np.ndarray:
    img = read_image(path)
    if img.ndim != 3:
        raise InputError("ground-truth normal map must be RGB (R = x, G = y, B = z)", path)
    if img.shape[:2] != shape:
        raise InputError(
            f"normal map is {img.shape[1]}×{img.shape[0]} but the images are {shape[1]}×{shape[0]}",
            path,
        )
    if img.dtype == np.uint16:
        full = 65535.0
    elif img.dtype == np.uint8:
        full = 255.0
    else:
        full = 1.0
    n = img.astype(np.float32) * np.float32(2.0 / full) - np.float32(1.0)
    length = np.linalg.norm(n, axis=2, keepdims=True)
    unit = np.abs(length - 1.0) <= _UNIT_TOLERANCE
    return np.where(unit, n / np.where(unit, length, 1.0), 0.0).astype(np.float32)


def _read_normal_mat(path: Path, shape: tuple[int, int]) -> np.ndarray:
    what = "ground-truth normals file"
    data = read_input_file(path, what, max_bytes=_MAT_BYTES_PER_PIXEL * shape[0] * shape[1] + _MAT_HEADERS)
    from scipy.io import loadmat, whosmat

    try:
        # The variables' shapes first: only the normals, of the photographs' size, are
        # inflated, so a small compressed file cannot claim gigabytes.
        found = {name: tuple(dims) for name, dims, _ in whosmat(io.BytesIO(data))}
        arrays = [k for k, dims in found.items() if len(dims) == 3]
        name = "Normal_gt" if "Normal_gt" in found else arrays[0] if len(arrays) == 1 else None
        fits = name is not None and found[name] == (*shape, 3)
        n = loadmat(io.BytesIO(data), variable_names=[name])[name] if fits else None
    except Exception as exc:  # scipy raises several types for a corrupt or v7.3 file
        raise InputError(f"cannot read {what} ({exc})", path) from None
    if n is None:
        got = "no H×W×3 array 'Normal_gt'" if name is None else f"an array of shape {found[name]}"
        raise InputError(f"expected normals of shape {(*shape, 3)}, found {got}", path)
    n = np.asarray(n, dtype=np.float32)
    length = np.linalg.norm(n, axis=2, keepdims=True)
    unit = np.abs(length - 1.0) <= _UNIT_TOLERANCE
    # NaN stays NaN (where the file says "unknown"); anything else that is not a unit vector
    # becomes zero, like the background of the PNG.
    return np.where(unit | np.isnan(length), n / np.where(unit, length, 1.0), 0.0).astype(np.float32)


def read_ps_dataset(
    folder: str | os.PathLike,
    *,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
    divide_intensities: bool = True,
) -> PSDataset:
    """Read a photometric-stereo dataset folder (DiLiGenT layout).

    Parameters
    ----------
    folder : str or PathLike
        The dataset folder (or its ``light_directions.txt``).
    threads : int, optional
        Decoding threads; default: the number of CPUs. Each holds one photograph at a time.
    progress : callable, optional
        Called with 1 after each photograph.
    divide_intensities : bool
        Divide the photographs by ``light_intensities.txt`` (default). False keeps them as
        stored: for intensities estimated from the photographs, or given otherwise.

    Returns
    -------
    PSDataset
        Lights, intensities, mask, ground truth and the stack with the intensities divided
        out per channel before the luminance reduction. Images are taken as linear (8-bit
        ones too: photometric-stereo datasets store linear radiance).

    Raises
    ------
    InputError
        Naming the file at fault: a missing file or folder; ``filenames.txt``,
        ``light_directions.txt`` and ``light_intensities.txt`` listing different counts;
        a line that is not numbers; an intensity that is zero or negative; a light at or below
        the horizon; fewer than three images; images, mask or normal map of different sizes;
        an image that cannot be decoded.
    """
    folder = Path(folder)
    if folder.is_file() and folder.name == DIRECTIONS:
        folder = folder.parent
    if not folder.exists():
        raise InputError("dataset folder not found", folder)
    if not folder.is_dir():
        raise InputError("not a folder (expected a photometric-stereo dataset folder)", folder)

    directions_path = folder / DIRECTIONS
    raised: list[str] = []
    dirs = _read_directions(directions_path, raised)
    n = len(dirs)
    paths = _read_filenames(folder, n)
    if len(paths) != n:
        raise InputError(
            f"lists {len(paths)} images but {DIRECTIONS} lists {n} lights", folder / FILENAMES
        )
    intensities = _read_intensities(folder / INTENSITIES, n)
    if n < MIN_PHOTOGRAPHS:
        raise InputError(f"lists {n} light(s); at least {MIN_PHOTOGRAPHS} photographs are needed to recover normals",
                         directions_path)
    for p in paths:
        if not p.is_file():
            raise InputError("image not found (listed in filenames.txt)", p)

    # Dividing by an intensity below 1 could push a bright sample past the top of the stored
    # range; one global factor keeps every sample representable and changes only the albedo.
    scale = float(min(1.0, intensities.min())) if divide_intensities else 1.0
    gains = scale / intensities if divide_intensities else None  # (N, 3), all ≤ 1

    first = read_image(paths[0])
    h, w = first.shape[:2]
    # Small files first, so that a wrong mask or normal map is reported before minutes of decoding.
    # A broken link or a folder in a file's place is reported, not taken for no file.
    mask = _read_mask(folder / MASK, (h, w)) if os.path.lexists(folder / MASK) else None
    if os.path.lexists(folder / NORMALS_PNG):
        normals = _decode_normal_png(folder / NORMALS_PNG, (h, w))
    elif os.path.lexists(folder / NORMALS_MAT):
        normals = _read_normal_mat(folder / NORMALS_MAT, (h, w))
    else:
        normals = None
    # Photometric-stereo datasets store linear radiance, 8-bit ones too.
    stack = load_stack(paths, linearize=False, channel_gains=gains, threads=threads, progress=progress)

    lights = LightSet(paths=paths, directions=dirs, source=directions_path,
                      warnings=tuple(f"{DIRECTIONS} {w}" for w in raised))
    return PSDataset(folder, lights, intensities, scale, mask, normals, stack)
