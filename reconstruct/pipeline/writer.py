"""Files written in background threads while the run goes on computing.

A run's files (1.3 GB at 24 megapixels: PNGs deflated, the OBJ's text, the PLY) took 2.8 s
after the mesh, and the page 1 s after them, each stage using about 1.4 of the 2 cores. With
a :class:`FileWriter` a run hands each file over as soon as its data exists (the maps after
the albedo, the height map after integrating, the meshes after meshing) and integrates,
meshes and makes the page while they are written; it waits for them before ``report.json``.

An error in a file's job (a full disk) is raised in the run's thread by
:meth:`FileWriter.check` between stages, or by :meth:`FileWriter.wait` (or
:meth:`FileWriter.wait_for`). Leaving the ``with`` block on an error cancels the jobs not yet
started and waits for those running, so nothing is written into a staging folder after it is
removed.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

from ptmcore.resources import thread_count

__all__ = ["FileWriter"]


class FileWriter:
    """Runs file-writing jobs in threads; each job is known by the file names it writes.

    Parameters
    ----------
    threads : int, optional
        Threads writing at once (default: the number of CPUs). The caller's thread keeps
        computing beside them.

    Examples
    --------
    >>> with FileWriter(2) as writer:                      # doctest: +SKIP
    ...     writer.submit(["normals.npy"], np.save, "normals.npy", normals)
    ...     height = integrate(normals)                    # while normals.npy is written
    ...     names = writer.wait()
    """

    def __init__(self, threads: int | None = None) -> None:
        self._pool = ThreadPoolExecutor(max_workers=thread_count(threads),
                                        thread_name_prefix="reconstruct-write")
        self._jobs: list[tuple[tuple[str, ...], Future]] = []
        self._lock = threading.Lock()

    def submit(self, names: list[str] | tuple[str, ...], fn: Callable, *args, **kwargs) -> list[str]:
        """Start ``fn(*args, **kwargs)``, which writes the files ``names``; return ``names``."""
        with self._lock:
            self._jobs.append((tuple(names), self._pool.submit(fn, *args, **kwargs)))
        return list(names)

    @property
    def names(self) -> list[str]:
        """Every file submitted so far, written or not, in submission order."""
        with self._lock:
            return [name for names, _ in self._jobs for name in names]

    def wait_for(self, name: str) -> None:
        """Return once the job writing ``name`` is done (at once if none writes it); raise its
        error if it failed."""
        with self._lock:
            futures = [f for names, f in self._jobs if name in names]
        for future in futures:
            future.result()

    def check(self) -> None:
        """Raise the error of the first job (in submission order) that has already failed, if
        any, without waiting: a full disk stops the run between stages, not at its end."""
        with self._lock:
            jobs = list(self._jobs)
        for _, future in jobs:
            if future.done() and not future.cancelled() and future.exception() is not None:
                raise future.exception()

    def wait(self) -> list[str]:
        """Wait for every job; raise the first failed job's error (in submission order);
        return the names written."""
        with self._lock:
            jobs = list(self._jobs)
        for _, future in jobs:
            future.result()
        return [name for names, _ in jobs for name in names]

    def close(self, *, cancel: bool = False) -> None:
        """Stop the threads once their jobs are done; with ``cancel`` the jobs not yet started
        are dropped."""
        self._pool.shutdown(wait=True, cancel_futures=cancel)

    def __enter__(self) -> FileWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.close(cancel=True)  # the caller's error is the one that counts
            return
        try:
            self.wait()
        finally:
            self.close(cancel=True)
