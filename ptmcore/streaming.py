"""Streaming a capture's photographs, one at a time, in their own encoding.

The fits that viewers' files need (HP's PTM, RTIBuilder's HSH) work on the photographs as they
are encoded, not on the linear stack the normals use, and add each photograph into running
per-pixel sums. These helpers decode the photographs a few at a time in threads and hand them
over in order, so memory stays at the sums plus a few photographs.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from .bands import run_bands
from .errors import InputError
from .images import read_image


def _as_image(img: np.ndarray, where: str) -> np.ndarray:
    """Check a photograph's layout: ``(H, W)`` or ``(H, W, 3)``, 8/16-bit or float."""
    a = np.asarray(img)
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (1, 3)):
        raise ValueError(f"{where}: expected an (H, W) or (H, W, 3) image, not {a.shape}")
    if a.dtype not in (np.uint8, np.uint16) and a.dtype.kind != "f":
        raise ValueError(f"{where}: unsupported sample type {a.dtype}")
    return a


def encoded_rows(block: np.ndarray) -> np.ndarray:
    """Rows of a photograph as float32 ``(rows, W, 3)`` in 8-bit units (0..255)."""
    if block.dtype == np.uint8:
        out = block.astype(np.float32)
    elif block.dtype == np.uint16:
        out = block.astype(np.float32) * np.float32(1 / 257)  # 65535 ↦ 255
    else:
        out = block.astype(np.float32) * np.float32(255)
    if out.ndim == 2:
        out = out[..., None]
    return np.repeat(out, 3, axis=2) if out.shape[2] == 1 else out


def stream_photographs(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray, threads: int | None
) -> Iterator[tuple[int, np.ndarray, Path | None]]:
    """Yield ``(k, image, path)`` in order, decoding files a few at a time in threads."""
    items = [images[k] for k in range(len(images))] if isinstance(images, np.ndarray) else list(images)
    if not any(isinstance(x, (str, os.PathLike)) for x in items):
        for k, x in enumerate(items):
            yield k, _as_image(x, f"image {k}"), None
        return

    def load(x: str | os.PathLike | np.ndarray) -> np.ndarray:
        return read_image(x) if isinstance(x, (str, os.PathLike)) else np.asarray(x)

    workers = max(1, threads or os.cpu_count() or 1)
    # At most `workers` decoded photographs wait at a time, so memory stays bounded.
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: list[Future] = [pool.submit(load, x) for x in items[:workers]]
        try:
            for k, x in enumerate(items):
                img = pending.pop(0).result()
                if k + workers < len(items):
                    pending.append(pool.submit(load, items[k + workers]))
                path = Path(x) if isinstance(x, (str, os.PathLike)) else None
                yield k, _as_image(img, str(path) if path else f"image {k}"), path
        finally:
            for f in pending:
                f.cancel()


def check_same_size(img: np.ndarray, shape: tuple[int, int], k: int, path: Path | None) -> None:
    if img.shape[:2] != shape:
        raise InputError(
            f"image is {img.shape[1]}×{img.shape[0]} but the first photograph is "
            f"{shape[1]}×{shape[0]}; all photographs of a capture must have the same size",
            path if path is not None else f"image {k}",
        )


def accumulate_photographs(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
    allocate: Callable[[tuple[int, int]], None],
    add: Callable[[int, np.ndarray, int, int], None],
    *,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> tuple[int, int]:
    """Stream the photographs into running per-pixel sums; return the image shape.

    ``allocate(shape)`` is called once with the first photograph's (H, W); then, for every
    photograph k, ``add(k, rows, r0, r1)`` gets its rows ``r0:r1`` in 0..255 units
    (:func:`encoded_rows`). Bands of rows never overlap, so threads add one photograph's bands
    at once.
    """
    shape: tuple[int, int] | None = None
    for k, img, path in stream_photographs(images, threads):
        if shape is None:
            shape = img.shape[:2]
            allocate(shape)
        check_same_size(img, shape, k, path)
        run_bands(shape[0], max(1, (1 << 18) // shape[1]),
                  lambda r0, r1, k=k, img=img: add(k, encoded_rows(img[r0:r1]), r0, r1), threads=threads)
        if progress is not None:
            progress(1)
    if shape is None:
        raise InputError("no photographs given")
    return shape


def fit_channels(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
    matrix: np.ndarray,
    *,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """Per-channel linear fit of the photographs as encoded: ``matrix`` (K, N) times each
    channel's values in 0..255 units, streamed one photograph at a time.

    Returns
    -------
    ndarray, shape (H, W, 3, K), float32
    """
    m = np.asarray(matrix, dtype=np.float32)
    k_terms = m.shape[0]
    sums: list[np.ndarray] = []

    def allocate(shape: tuple[int, int]) -> None:
        # Plane by plane: adding into an interleaved (..., K) array makes NumPy loop over the
        # short last axis and runs several times slower.
        sums.append(np.zeros((3, k_terms) + shape, dtype=np.float32))

    def add(k: int, c: np.ndarray, r0: int, r1: int) -> None:
        acc = sums[0]
        for ch in range(3):
            for j in range(k_terms):
                acc[ch, j, r0:r1] += c[..., ch] * m[j, k]

    accumulate_photographs(images, allocate, add, threads=threads, progress=progress)
    return np.ascontiguousarray(np.moveaxis(sums[0], (0, 1), (2, 3)))
