"""A stack in a file, whose pages leave the process as soon as a band of rows is done.

A 24-megapixel capture of 48 JPEGs is a 1.15 GB stack of 8-bit codes, held while the fits'
sums (1.3 GB) are added up. In a file-backed mapping the stack's pages belong to the operating
system's page cache: once a band has been written (decoding) or read (photometric stereo),
:func:`release_rows` tells the kernel the process no longer needs them (``MADV_DONTNEED`` on a
shared file mapping drops the pages from the process, never the data), so they stop counting in
the run's resident memory. The cache keeps them while memory is free — reading a band back is
then a copy from memory, measured as fast as an array in the process (BENCHMARKS.md) — and
writes them to the file when memory is short, where an array in the process could only make the
machine swap or kill the run.

The file is in a folder the caller chooses (the run's staging folder) and is unlinked as soon as
it is mapped, so nothing is left behind however the process ends.
"""

from __future__ import annotations

import ctypes
import errno
import mmap
import os
import shutil
import tempfile

import numpy as np

from .errors import InputError

__all__ = ["disk_array", "is_disk_array", "release_rows", "resident_bytes"]


def disk_array(folder: str | os.PathLike, shape: tuple[int, ...], dtype: type) -> np.memmap:
    """An uninitialised C-ordered array backed by a file in ``folder``.

    The file is removed from the folder as soon as it is mapped: the mapping keeps its data
    until the array is released, and nothing is left behind when the process ends, however
    it ends.
    """
    nbytes = max(1, int(np.prod(shape)) * np.dtype(dtype).itemsize)
    fd, name = tempfile.mkstemp(prefix=".stack-", suffix=".raw", dir=folder)
    try:
        _reserve(fd, nbytes, folder)
        array = np.memmap(name, dtype=dtype, mode="r+", shape=shape)
    finally:
        os.close(fd)
        os.unlink(name)
    return array


def _reserve(fd: int, nbytes: int, folder: str | os.PathLike) -> None:
    """Give the file its blocks now: a write through the mapping into a sparse file on a full
    disk would kill the process (SIGBUS) at some later page instead of failing here."""
    full = False
    try:
        os.posix_fallocate(fd, 0, nbytes)
        return
    except OSError as exc:  # other errors: a file system without allocation (checked below)
        full = exc.errno == errno.ENOSPC
    except AttributeError:  # no posix_fallocate on this platform (e.g. macOS)
        pass
    if full or shutil.disk_usage(folder).free < nbytes:
        raise InputError(
            f"no room for the photographs' stack ({nbytes / 2**30:.1f} GB) on this disk: free some "
            "space, or give a --memory-limit large enough to keep it in memory", folder)
    os.ftruncate(fd, nbytes)


def is_disk_array(array: np.ndarray) -> bool:
    """Whether ``array`` is a whole array made by :func:`disk_array` (a shared, writable file
    mapping in C order), the only kind whose pages :func:`release_rows` may drop: on a private
    or anonymous mapping ``MADV_DONTNEED`` would discard the data itself."""
    mm = getattr(array, "_mmap", None)
    return (isinstance(array, np.memmap) and isinstance(mm, mmap.mmap) and array.mode == "r+"
            and array.flags.c_contiguous and array.offset == 0 and array.nbytes == len(mm)
            and hasattr(mm, "madvise"))


def release_rows(array: np.ndarray, r0: int, r1: int, planes: range | None = None) -> None:
    """Drop rows ``r0:r1`` of ``planes`` (default: all) of a stack (N, H, W) made by
    :func:`disk_array` from the process's memory; their data stays in the file (and in the
    page cache while memory allows). Does nothing for any other array.

    Only whole pages inside each plane's rows are dropped, so a page shared with a band another
    thread is working on is never touched; the few pages at band edges stay until
    :func:`release_rows` is called on the whole height.
    """
    if not is_disk_array(array) or array.ndim != 3:
        return
    mm = array._mmap
    n, h, w = array.shape
    row = w * array.itemsize
    page = mmap.PAGESIZE
    # The array starts where the mapping does (offset 0, checked by is_disk_array).
    for k in planes if planes is not None else range(n):
        lo = (k * h + r0) * row
        hi = (k * h + r1) * row
        lo = -(-lo // page) * page
        hi = hi // page * page
        if hi > lo:
            mm.madvise(mmap.MADV_DONTNEED, lo, hi - lo)


def resident_bytes(array: np.ndarray) -> int:
    """Bytes of ``array``'s file mapping resident in the process (``mincore`` counts the page
    cache, so this reads ``/proc/self/smaps`` instead); 0 for any other array. For tests."""
    if not is_disk_array(array):
        return 0
    start = ctypes.addressof(ctypes.c_char.from_buffer(array._mmap))
    with open("/proc/self/smaps") as f:
        inside = False
        for line in f:
            head = line.split(None, 1)[0]
            if "-" in head and not head.endswith(":"):
                lo = int(head.split("-")[0], 16)
                inside = lo == start
            elif inside and head == "Rss:":
                return int(line.split()[1]) * 1024
    return 0
