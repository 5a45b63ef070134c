"""Processing images in bands of rows, in parallel threads.

The per-pixel stages (PTM fit, photometric stereo, albedo) are matrix products and element-wise
NumPy work on one band at a time, so memory stays bounded however large the capture is. NumPy
releases the GIL in that work, so bands run in threads without copying the stack.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from threadpoolctl import threadpool_limits

from .resources import thread_count

#: Default memory for one band of the stack as float32.
BAND_BYTES = 32 << 20


def band_rows(n_images: int, width: int, bytes_per_sample: int = 4, budget: int = BAND_BYTES) -> int:
    """Rows per band so that one band of the stack takes about ``budget`` bytes."""
    return max(1, int(budget // max(1, n_images * width * bytes_per_sample)))


def run_bands(
    height: int,
    rows: int,
    work: Callable[[int, int], None],
    *,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> None:
    """Call ``work(r0, r1)`` for consecutive bands of ``rows`` rows covering ``height``.

    Parameters
    ----------
    height : int
        Number of rows.
    rows : int
        Rows per band.
    work : callable
        Processes rows ``r0:r1`` and stores its results itself (bands never overlap).
    threads : int, optional
        Worker threads; default: the number of CPUs.
    progress : callable, optional
        Called with the number of rows of each finished band.

    Notes
    -----
    While bands run in several threads, BLAS is held to one thread (``threadpoolctl``, for the
    whole process): each band's matrix products are small, and OpenBLAS starting its own
    threads inside every band's thread made two threads no faster than one (2.7 s both, a
    6-megapixel PTM fit).
    """
    bands = [(r0, min(height, r0 + rows)) for r0 in range(0, height, rows)]
    workers = min(len(bands), thread_count(threads))

    def one(band: tuple[int, int]) -> int:
        work(*band)
        return band[1] - band[0]

    if workers <= 1:
        for band in bands:
            done = one(band)
            if progress is not None:
                progress(done)
        return
    with threadpool_limits(limits=1, user_api="blas"), ThreadPoolExecutor(max_workers=workers) as pool:
        for done in pool.map(one, bands):
            if progress is not None:
                progress(done)
