"""Streaming a capture's photographs through per-pixel sums, each photograph decoded once.

The fits that viewers' files need (HP's PTM, RTIBuilder's HSH) and the linear stack the normals
use are all built photograph by photograph into per-pixel arrays (:mod:`ptmcore.reduce`). This
module schedules that work: threads decode a few photographs each and add them into the arrays
a band of rows at a time, so memory stays at the arrays plus a few photographs.

The float32 sums must be added in photograph order, or their last bits (and so a ``.ptm``
file's bytes) would depend on the threads' timing. Bands of rows never overlap, so a band is
the unit of ownership: :class:`BandTurns` lets a task add band ``b`` only after the task before
it has added its own band ``b``. A task whose photographs are decoded follows the one before it
band by band, instead of waiting for it to finish: decoding the next photographs overlaps the
reduction of these, with no lock on the sums and no lost update.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from pathlib import Path

import numpy as np

from .errors import InputError
from .images import read_image

__all__ = ["BandTurns", "Photographs", "check_same_size", "run_in_order"]


def _as_image(img: np.ndarray, where: str) -> np.ndarray:
    """Check a photograph's layout: ``(H, W)`` or ``(H, W, 3)``, 8/16-bit or float."""
    a = np.asarray(img)
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (1, 3)):
        raise ValueError(f"{where}: expected an (H, W) or (H, W, 3) image, not {a.shape}")
    if a.dtype not in (np.uint8, np.uint16) and a.dtype.kind != "f":
        raise ValueError(f"{where}: unsupported sample type {a.dtype}")
    return a


class Photographs:
    """A capture's photographs as files or arrays, decoded one at a time on demand.

    Parameters
    ----------
    images : sequence of path or ndarray, or ndarray (N, H, W[, 3])
        Files are read with :func:`ptmcore.images.read_image`; arrays are checked
        (``(H, W)`` or ``(H, W, 3)``, uint8, uint16 or float).
    """

    def __init__(self, images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray) -> None:
        self.items = [images[k] for k in range(len(images))] if isinstance(images, np.ndarray) else list(images)

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
            return read_image(path, buffer=buffer)
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


class _Aborted(Exception):
    """A task gave up because another one failed."""


class BandTurns:
    """Per-band order of the tasks: task ``t`` adds band ``b`` after task ``t − 1`` has.

    Tasks are numbered in photograph order and started in that order, so the task a waiter
    waits for is running or done, and the waits cannot deadlock; :meth:`fail` wakes and aborts
    every waiter when a task fails.
    """

    def __init__(self, bands: int) -> None:
        self._done = [0] * bands
        self._cond = threading.Condition()
        self._failed = False

    def wait(self, band: int, task: int) -> None:
        """Block until ``task`` may add ``band``; raise if another task failed."""
        with self._cond:
            while self._done[band] < task and not self._failed:
                self._cond.wait()
            if self._failed:
                raise _Aborted

    def finish(self, band: int) -> None:
        """The current task has added ``band``."""
        with self._cond:
            self._done[band] += 1
            self._cond.notify_all()

    def fail(self) -> None:
        """Abort every task that waits now or later."""
        with self._cond:
            self._failed = True
            self._cond.notify_all()


def run_in_order(
    n: int,
    batch: int,
    prepare: Callable[[int], object],
    add: Callable[[list, int, int], None],
    bands: list[tuple[int, int]],
    *,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
    release: Callable[[list], None] | None = None,
) -> None:
    """Add ``n`` photographs, ``batch`` at a time, into per-pixel arrays in photograph order.

    Each task takes ``batch`` consecutive photographs: it calls ``prepare(k)`` for each (decode
    and check; the results stay in memory until the task ends), then ``add(prepared, r0, r1)``
    for every band of ``bands`` in its turn (:class:`BandTurns`), then ``release(prepared)``
    (e.g. to reuse the photographs' memory). At most ``threads`` tasks run at a time, so at
    most ``threads · batch`` photographs are held. ``progress(1)`` is called for each
    photograph when its task is done.

    Raises
    ------
    Exception
        The first error, in photograph order, of a task that failed; the tasks not yet started
        are cancelled.
    """
    tasks = [(k0, min(n, k0 + batch)) for k0 in range(0, n, batch)]
    turns = BandTurns(len(bands))

    def task(t: int) -> None:
        k0, k1 = tasks[t]
        prepared: list = []
        try:
            for k in range(k0, k1):
                prepared.append(prepare(k))
            for b, (r0, r1) in enumerate(bands):
                turns.wait(b, t)
                add(prepared, r0, r1)
                turns.finish(b)
        except BaseException:
            turns.fail()
            raise
        finally:
            if release is not None:
                release(prepared)
            del prepared
        if progress is not None:
            for _ in range(k1 - k0):
                progress(1)

    workers = max(1, min(len(tasks), threads or os.cpu_count() or 1))
    if workers == 1:
        for t in range(len(tasks)):
            task(t)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = [pool.submit(task, t) for t in range(len(tasks))]
        wait(futures, return_when=FIRST_EXCEPTION)
        for f in futures:
            f.cancel()
    # The first real error in photograph order: tasks that only gave up (_Aborted) because
    # another failed, and cancelled ones, are not it.
    for f in futures:
        if not f.cancelled() and f.exception() is not None and not isinstance(f.exception(), _Aborted):
            raise f.exception()
