"""Streaming a capture's photographs through per-pixel sums, each photograph decoded once.

The fits that viewers' files need (HP's PTM, RTIBuilder's HSH) and the linear stack the normals
use are all built photograph by photograph into per-pixel arrays (:mod:`ptmcore.reduce`). This
module schedules that work: the threads decode a group of photographs together, then add the
group into the arrays together, each thread a band of rows at a time, so memory stays at the
arrays plus one group of photographs.

The float32 sums must be added in photograph order, or their last bits (and so a ``.ptm``
file's bytes) would depend on the threads' timing. Bands of rows never overlap and one call
adds a whole group to a band, photograph after photograph, so the order holds without a lock.
Adding a group at once rather than each thread its own photographs matters for speed: the
sums (14 float32 per pixel, 1.3 GB at 24 megapixels) are read and written once per group, and
that memory traffic was most of the reduction's time.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import InputError
from .images import read_image
from .resources import thread_count

if TYPE_CHECKING:
    from .raw import RawDevelopment

__all__ = ["Photographs", "check_same_size", "run_in_groups"]


def _as_image(img: np.ndarray, where: str) -> np.ndarray:
    """Check a photograph's layout: ``(H, W)`` or ``(H, W, 3)``, 8/16-bit or float."""
    a = np.asarray(img)
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (1, 3)):
        raise ValueError(f"{where}: expected an (H, W) or (H, W, 3) image, not {a.shape}")
    if a.dtype not in (np.uint8, np.uint16) and a.dtype.kind != "f":
        raise ValueError(f"{where}: unsupported sample type {a.dtype}")
    # As read_image refuses them in files: the kernels' clipping does not tell NaN from a
    # sample, and a NaN luminance code would index out of the 8-bit stack's table.
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise ValueError(f"{where}: contains NaN or infinite values")
    return a


class Photographs:
    """A capture's photographs as files or arrays, decoded one at a time on demand.

    Parameters
    ----------
    images : sequence of path or ndarray, or ndarray (N, H, W[, 3])
        Files are read with :func:`ptmcore.images.read_image`; arrays are checked
        (``(H, W)`` or ``(H, W, 3)``, uint8, uint16 or float).
    raw : RawDevelopment, optional
        How camera RAW files are developed, all alike (:func:`ptmcore.raw.raw_development`
        of the capture's first photograph); default: each file's own.
    """

    def __init__(self, images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
                 raw: RawDevelopment | None = None) -> None:
        self.items = [images[k] for k in range(len(images))] if isinstance(images, np.ndarray) else list(images)
        self.raw = raw

    def __len__(self) -> int:
        return len(self.items)

    def path(self, k: int) -> Path | None:
        """The file of photograph ``k``, or None for an array."""
        x = self.items[k]
        return Path(x) if isinstance(x, (str, os.PathLike)) else None

    def load(self, k: int, buffer: np.ndarray | None = None) -> np.ndarray:
        """Photograph ``k`` as stored (see :func:`ptmcore.images.read_image`, which may
        decode it into ``buffer``)."""
        path = self.path(k)
        if path is not None:
            return read_image(path, buffer=buffer, raw=self.raw)
        return _as_image(self.items[k], f"image {k}")


def check_same_size(img: np.ndarray, shape: tuple[int, int], k: int, path: Path | None,
                    first: Path | None = None) -> None:
    """Raise :class:`InputError` unless photograph ``k`` is ``shape`` (H, W) like the first."""
    if img.shape[:2] != shape:
        name = first.name if first is not None else "the first photograph"
        raise InputError(
            f"image is {img.shape[1]}×{img.shape[0]} but {name} is {shape[1]}×{shape[0]}; "
            "all photographs of a capture must have the same size",
            path if path is not None else f"image {k}",
        )


def run_in_groups(
    n: int,
    group: int,
    prepare: Callable[[int], object],
    add: Callable[[list, int, int], None],
    bands: list[tuple[int, int]],
    *,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
    release: Callable[[list], None] | None = None,
) -> None:
    """Add ``n`` photographs, ``group`` at a time, into per-pixel arrays in photograph order.

    For each group of consecutive photographs the threads first ``prepare(k)`` them (decode and
    check), then call ``add(prepared, r0, r1)`` for the bands of ``bands`` (each band by one
    thread; the group's photographs in order inside the call), then ``release(prepared)`` (e.g.
    to reuse the photographs' memory). So at most ``group`` photographs are held, each pixel's
    sums are read and written once per group, and a float32 sum never depends on the threads'
    timing. ``progress(1)`` is called for each photograph when its group is added.

    Raises
    ------
    Exception
        The first error in photograph order; later groups are not started.
    """
    workers = thread_count(threads)
    pool = ThreadPoolExecutor(max_workers=workers) if workers > 1 else None
    each = pool.map if pool is not None else map
    try:
        for k0 in range(0, n, group):
            prepared: list = []
            try:
                # Collected in order, so the first failure in photograph order is raised.
                for item in each(prepare, range(k0, min(n, k0 + group))):
                    prepared.append(item)
                for _ in each(lambda band: add(prepared, *band), bands):
                    pass
            finally:
                if release is not None:
                    release(prepared)
            if progress is not None:
                for _ in prepared:
                    progress(1)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
