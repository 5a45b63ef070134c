"""A batch on Dask's distributed scheduler: the cluster, the lock, the tasks and their rows.

:func:`run_batch` is what ``reconstruct batch`` calls. Without a client or a scheduler address
it starts a local cluster of worker processes sized for this machine (:func:`choose_workers`):
a worker killed by the operating system, for memory say, is replaced and its object retried
once by Dask, then reported as failed. Interrupted, a batch cancels its tasks and stops its
objects running on the workers (:func:`reconstruct.batch.runner.stop_objects`).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import secrets
import signal
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

from ptmcore.atomic import name_max
from ptmcore.errors import InputError, first_few
from ptmcore.resources import available_memory_mb, cpu_count
from reconstruct.batch.rows import FAILED, BatchItem, BatchRow, write_rows
from reconstruct.batch.runner import already_done, choose_workers, describe_failure, run_object, stop_objects
from reconstruct.batch.sources import discover, read_manifest
from reconstruct.pipeline.options import RunOptions

__all__ = ["LOCK_NAME", "batch_lock", "collect_items", "run_batch"]

LOCK_NAME = ".batch.lock"
#: Tries of an object whose worker died, after the first (the local cluster's setting; an
#: existing scheduler has its own, distributed.scheduler.allowed-failures).
RETRIES = 1
#: The local cluster's settings. Dask's statistical profiler is off: it calls
#: ``sys._current_frames()`` every 10 ms, and on CPython 3.11 a garbage collection during that
#: call that frees a ``threading.local`` deadlocks the worker (the interpreter's thread-list
#: lock taken twice by one thread: seen as a batch test hung for good, at 0 % CPU, in gdb
#: ``local_clear`` waiting on the lock ``_current_frames`` held). Nothing here reads the profiles.
LOCAL_CONFIG = {"distributed.scheduler.allowed-failures": RETRIES, "distributed.worker.profile.enabled": False}
#: How long a batch tries to reach a scheduler given by its address, in seconds.
CONNECT_SECONDS = 20
#: Bytes the batch adds to an object's name in names it cannot shorten: its thumbnails',
#: ``NAME_height.png`` (:data:`reconstruct.batch.gallery.THUMBNAILS`; an earlier version's
#: ``.replaced-NAME`` adds 10). Hidden names made beside a file or folder, a run's staging
#: folder and a temporary file, are shortened to fit (:func:`ptmcore.atomic.hidden_name`).
NAME_MARGIN = len("_height.png")


@contextmanager
def batch_lock(out: Path) -> Iterator[None]:
    """Hold ``out/.batch.lock`` for the batch; a second batch on ``out`` gets an InputError.

    An advisory lock (``flock``) on the file, which the batch removes as it ends, done, failed
    or interrupted (and ``out`` too, if the batch made it and it is still empty). A killed
    batch leaves the file, but the kernel released its lock with the process: the next batch
    takes it over.
    """
    made = not os.path.isdir(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot write the output folder ({exc.strerror})", out) from None
    try:
        fd = _lock(out / LOCK_NAME)
        try:
            yield
        finally:
            # Removed while still locked: a batch that opened it meanwhile finds it gone
            # once it has the lock, and locks a new file (_lock).
            with contextlib.suppress(OSError):
                os.unlink(out / LOCK_NAME)
            os.close(fd)
    finally:
        if made:
            with contextlib.suppress(OSError):
                out.rmdir()


def _lock(path: Path) -> int:
    """An open descriptor holding the ``flock`` of ``path``; InputError when another holds it.

    The file may be removed by the batch ending between our opening it and locking it: a lock
    on a file removed is no lock, so it is taken again on the file now at ``path``.
    """
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666)
        except OSError as exc:
            raise InputError(f"cannot write the output folder ({exc.strerror})", path.parent) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise InputError("another batch is writing into this folder (it holds .batch.lock); "
                             "wait for it or choose another output folder", path.parent) from None
        held = os.fstat(fd)
        try:
            now = os.stat(path, follow_symlinks=False)
        except FileNotFoundError:
            now = None
        if now is not None and (now.st_dev, now.st_ino) == (held.st_dev, held.st_ino):
            return fd
        os.close(fd)


def _check_names(items: list[BatchItem], out: Path) -> None:
    """Refuse object names longer than the output folder's file system takes, with the
    :data:`NAME_MARGIN` the batch adds: the object would fail only once a worker wrote it."""
    limit = name_max(out)
    longest = limit - NAME_MARGIN
    long = [f"{i.name[:40]}…" for i in items if len(os.fsencode(i.name)) > longest]
    if long:
        raise InputError(f"object name(s) too long: {first_few(long)}; the output folder's file system takes names of "
                         f"{limit} bytes, and the thumbnails add {NAME_MARGIN}, so at most {longest} bytes: give "
                         "shorter names in a manifest's name column", out)


def _check_scheduler_address(address: str) -> None:
    """Refuse a ``--scheduler`` that is not a Dask scheduler's address: a scheme Dask knows
    (``tcp://`` when none is given) and ``HOST:PORT``."""
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import get_backend

    try:
        scheme, location = parse_address(address)
        get_backend(scheme)
        host, port = parse_host_port(location)
        if not host:
            raise ValueError("no host")
        if not 0 < port < 65536:
            raise ValueError(f"port {port} is not within 1 to 65535")
    except ValueError as exc:
        shown = address if len(address) <= 80 else address[:79] + "…"
        raise InputError(f"--scheduler {shown!r} is not a Dask scheduler's address ({exc}); give it as "
                         "`dask scheduler` prints it, tcp://HOST:PORT") from None


def collect_items(sources: list[str | os.PathLike], options: RunOptions, manifest: str | os.PathLike | None,
                  echo: Callable[[str], None] = lambda line: None) -> list[BatchItem]:
    """The batch's objects from SOURCEs and/or a manifest, checked; says what was skipped."""
    items: list[BatchItem] = []
    if sources:
        found, skipped = discover(sources, options)
        items += found
        echo(f"found {len(found)} capture(s)" + (f", skipped {len(skipped)}:" if skipped else ""))
        for path, why in skipped:
            echo(f"  skipped {path}: {why}")
    if manifest is not None:
        rows = read_manifest(manifest, options)
        echo(f"manifest {manifest}: {len(rows)} object(s)")
        items += rows
    if not items:
        raise InputError("nothing to do: give capture folders, .ptm files or --manifest")
    names = [i.name.lower() for i in items]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise InputError(f"two objects would be written to the same folder: {', '.join(repeated)}; "
                         "give them names in the manifest")
    return items


def _wait_for_a_worker(client, timeout: float = 60.0) -> None:
    """An existing cluster may still be starting its workers (a Slurm job in the queue)."""
    try:
        client.wait_for_workers(1, timeout=timeout)
    except TimeoutError:
        raise InputError(f"no Dask worker joined the scheduler within {timeout:.0f} s") from None


@contextmanager
def _client(client, scheduler: str | None, items: list[BatchItem], workers: int | None,
            echo: Callable[[str], None]):
    """The Dask client to use, and the threads each object may take: the caller's client, one
    connected to ``scheduler``, or a local cluster's."""
    import dask
    from distributed import Client, LocalCluster

    # On an existing cluster a worker may run several objects at once (its --nthreads): each
    # object then takes one thread unless --threads says otherwise (docs/cluster.md).
    if client is not None:
        _wait_for_a_worker(client)
        yield client, 1
        return
    if scheduler is not None:
        try:
            remote = Client(scheduler, timeout=f"{CONNECT_SECONDS}s")
        except OSError as exc:
            raise InputError(f"cannot reach the Dask scheduler at {scheduler} ({exc})") from None
        except Exception as exc:  # noqa: BLE001 - whatever a server that is no Dask scheduler sends
            raise InputError(f"{scheduler} answered, but not as a Dask scheduler does ({type(exc).__name__}): "
                             "give the address `dask scheduler` prints") from None
        with remote:
            echo(f"Dask scheduler {scheduler}; dashboard: {remote.dashboard_link}")
            _wait_for_a_worker(remote)
            yield remote, 1
        return
    cores = cpu_count()
    n = choose_workers(items, cores, available_memory_mb(), workers, echo)
    threads = max(1, cores // n)
    # Worker processes isolate crashes and memory; the nanny restarts a worker the operating
    # system killed. One Dask thread each: an object's own threads do the parallel work.
    # A worker's death counts against its task: after RETRIES more, the object is failed
    # (Dask's default would run an object that exhausts the memory four times).
    with dask.config.set(LOCAL_CONFIG), ExitStack() as stack:
        with _ctrl_c_blocked():
            cluster = stack.enter_context(LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                       dashboard_address=":0", memory_limit=0, silence_logs=40))
        local = stack.enter_context(Client(cluster))
        echo(f"{n} worker(s) × {threads} thread(s); Dask dashboard: {local.dashboard_link}")
        try:
            yield local, threads
        finally:
            _quiet_workers(local)


@contextmanager
def _ctrl_c_blocked() -> Iterator[None]:
    """Block SIGINT in the calling thread while a local cluster starts.

    A terminal's Ctrl-C goes to every process of the foreground group, the cluster's workers
    too, each of which then printed a traceback. The batch's own process is the one to stop
    them (it closes the cluster). A signal mask, unlike a handler, is inherited by the
    threads a thread starts and kept across ``fork`` and ``exec``: the cluster's event-loop
    thread, started here, has SIGINT blocked, and so has every worker process it spawns, now
    or when it replaces a dead one. A Ctrl-C pressed meanwhile still reaches the batch: Python
    runs signal handlers in its main thread, at the latest once the mask is restored.
    """
    if not hasattr(signal, "pthread_sigmask"):  # pragma: no cover - not POSIX
        yield
        return
    # Started first: starting multiprocessing's resource tracker unblocks SIGINT in the
    # thread that starts it (CPython 3.11 unblocks rather than restores the mask), which
    # would be the cluster's event loop.
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _quiet_workers(client) -> None:
    """Stop the worker processes of ``client``'s local cluster logging below CRITICAL.

    Called as the cluster is about to close, after the batch has said all it has to say. A
    worker whose heartbeat is on its way when the scheduler closes logs the broken connection
    with a traceback at ERROR (a race of Dask's own shutdown, dask/distributed#7105), which
    then lands on the user's terminal after the batch's last line. Every object's outcome is in
    the batch's rows by then. The worker processes are the cluster's own and end with it, so
    their process-wide logging is theirs to change; the nannies and the scheduler run in the
    caller's process, whose logging stays as it is. Best effort, like :func:`_stop`.
    """
    try:
        client.run(_log_critical_only, on_error="ignore")
    except Exception:  # noqa: BLE001, S110 - a worker already gone prints nothing more
        pass


def _log_critical_only() -> None:
    import logging

    logging.disable(logging.ERROR)


def _check_shared_paths(client, out: Path, items: list[BatchItem]) -> None:
    """Every worker must see the captures and the output folder at the same paths."""
    paths = [str(out), *{str(i.source) for i in items}]

    def missing(paths: list[str]) -> list[str]:
        return [p for p in paths if not os.path.exists(p)]

    for worker, lost in client.run(missing, paths).items():
        if lost:
            raise InputError(f"the Dask worker {worker} cannot see {lost[0]}"
                             + (f" (and {len(lost) - 1} more)" if len(lost) > 1 else "")
                             + ": workers need the captures and the output folder on shared storage "
                             "at the same paths (docs/cluster.md)")


def _submit_all(client, items: list[BatchItem], out: Path, force: bool, threads: int,
                progress: Callable[[BatchRow, int, int], None] | None, counted: int = 0,
                total: int | None = None) -> list[BatchRow]:
    """One task per object; rows in the items' order, each reported as it finishes (the
    count starting after ``counted`` objects reported already, of ``total``).

    Interrupted (Ctrl-C), it cancels the objects not started and stops those running
    (:func:`_stop`) before the interruption goes on.
    """
    from distributed import as_completed

    token = secrets.token_hex(8)
    futures = {client.submit(run_object, item, out, force=force, threads=threads, token=token, pure=False,
                             retries=RETRIES, key=f"reconstruct-{k}-{item.name}"): k
               for k, item in enumerate(items)}
    rows: list[BatchRow | None] = [None] * len(items)
    try:
        for done, future in enumerate(as_completed(futures), counted + 1):
            k = futures[future]
            try:
                rows[k] = future.result()
            except Exception as exc:  # noqa: BLE001 - a dead worker (KilledWorker) or a lost task
                rows[k] = BatchRow(items[k].name, str(items[k].source), FAILED,
                                   "the worker running it died, also when retried (killed by the operating "
                                   f"system, perhaps for memory): {describe_failure(exc)}")
            if progress is not None:
                progress(rows[k], done, len(items) if total is None else total)
    except BaseException:
        _stop(client, list(futures), token)
        raise
    return rows


def _stop(client, futures: list, token: str) -> None:
    """Cancel a batch's tasks and stop its objects running on the workers.

    Closing a local cluster alone would wait for the running objects (the workers finish
    their task before they close) and then kill them, leaving their staging folders behind;
    on an existing cluster they would run on to the end. Stopped, each run removes its
    staging folder at its next step and the worker is free at once. Best effort: the
    interruption that called this is what the caller reports.
    """
    try:
        client.cancel(futures)
        client.run(stop_objects, token, on_error="ignore")
    except Exception:  # noqa: BLE001, S110 - a worker or scheduler already gone has nothing to stop
        pass


def run_batch(
    sources: list[str | os.PathLike] | None,
    out: str | os.PathLike,
    options: RunOptions | None = None,
    *,
    manifest: str | os.PathLike | None = None,
    client=None,
    scheduler: str | None = None,
    workers: int | None = None,
    force: bool = False,
    progress: Callable[[BatchRow, int, int], None] | None = None,
    echo: Callable[[str], None] = lambda line: None,
) -> list[BatchRow]:
    """Reconstruct many objects, one Dask task each; write ``batch.csv``, ``batch.json`` and
    ``index.html`` into ``out``.

    Parameters
    ----------
    sources : list of path or None
        Capture folders, ``.lp`` or ``.ptm`` files, or parent folders of captures.
    out : path
        The batch's folder: ``out/<name>/`` per object, exactly as ``reconstruct run`` writes it.
    options : RunOptions, optional
        Every object's options (a manifest row overrides them).
    manifest : path, optional
        A CSV with one row per object (:func:`reconstruct.batch.read_manifest`).
    client : distributed.Client, optional
        An existing Dask client; else ``scheduler`` or a local cluster.
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://host:8786``); its workers must see the
        same paths.
    workers : int, optional
        Workers of the local cluster (default, and at most: as many as cores and memory allow;
        ``echo`` is told when more are asked for).
    force : bool
        Redo objects whose output is complete and unchanged (default: skip them).
    progress : callable, optional
        ``progress(row, done, total)`` as each object finishes.
    echo : callable, optional
        Receives lines worth telling a user (what was found and skipped, the dashboard).

    Returns
    -------
    list of BatchRow
        In the order of the objects.

    Raises
    ------
    InputError
        For bad batch arguments (a source or manifest row, a name too long for ``out``'s file
        system, a scheduler address that is none or cannot be reached, paths the workers cannot
        see, another batch on ``out``), before any object runs.
    """
    from reconstruct.batch.gallery import write_index

    out = Path(out)
    opt = options or RunOptions()
    items = collect_items(list(sources or []), opt, manifest, echo)
    _check_names(items, out)
    if client is None and scheduler is not None:
        _check_scheduler_address(scheduler)
    with batch_lock(out):
        # What is done already is decided here, before any cluster starts: a finished batch
        # run again starts none.
        rows: list[BatchRow | None] = [None if force else already_done(i, out.resolve()) for i in items]
        skipped = [row for row in rows if row is not None]
        for done, row in enumerate(skipped, 1):
            if progress is not None:
                progress(row, done, len(items))
        todo = [k for k, row in enumerate(rows) if row is None]
        if todo:
            with _client(client, scheduler, [items[k] for k in todo], workers, echo) as (dask, threads):
                _check_shared_paths(dask, out.resolve(), [items[k] for k in todo])
                threads = opt.threads or threads
                run = [items[k] if items[k].options.threads else _with_threads(items[k], threads) for k in todo]
                for k, row in zip(todo, _submit_all(dask, run, out.resolve(), force, threads, progress,
                                                    len(skipped), len(items))):
                    rows[k] = row
        write_rows(out, rows)
        write_index(out, rows, title=f"Batch: {out.resolve().name}")
    return rows


def _with_threads(item: BatchItem, threads: int) -> BatchItem:
    import dataclasses

    return dataclasses.replace(item, options=dataclasses.replace(item.options, threads=threads))
