"""How the command stops: Ctrl-C (SIGINT) once or twice, and SIGTERM.

The standard library only, so that the entry point (:mod:`reconstruct.cli.console`) sets these
handlers up before the command's own imports, and keeps them until the process ends: between
``main`` returning and the process's exit there is then no moment when Python's own handler is
back, where a late Ctrl-C would raise a second KeyboardInterrupt (and a second message, or a
traceback).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: Ended by Ctrl-C (SIGINT): 128 + 2, as a shell reports a process the signal stopped.
EXIT_INTERRUPTED = 130
#: Ended by SIGTERM: 128 + 15, as a shell reports a process the signal killed.
EXIT_TERMINATED = 143


def interrupted() -> int:
    """Say that Ctrl-C stopped the command; its exit status.

    Called once what the runs staged is removed. From here on a further Ctrl-C (a second press,
    or one that was on its way) ends the process at once and says nothing more.
    """
    if signal.getsignal(signal.SIGINT) in (_interrupt, _terminate) and _in_main_thread():
        signal.signal(signal.SIGINT, _quiet)
    # One write: a handler that ran between print()'s text and its newline split the line.
    sys.stderr.write("reconstruct: interrupted\n")
    sys.stderr.flush()
    return EXIT_INTERRUPTED


def _quiet(signum: int, frame) -> None:
    """Ctrl-C after :func:`interrupted` has spoken: nothing is left to clean up or to say."""
    os._exit(EXIT_INTERRUPTED)


#: Set by the first :func:`_terminate`: the process is removing what it staged and will end.
_stopping = False


def _terminate(signum: int, frame) -> None:
    """SIGTERM (a scheduler's or ``kill``'s stop), or a second Ctrl-C: remove what the runs in
    progress staged and end at once. Not an exception unwinding the stack, as a first Ctrl-C is:
    one raised wherever the main thread happens to be (inside an import, say) can leave a lock
    held and the process hung. Output folders keep their earlier results: they only change by
    one rename."""
    global _stopping
    if _stopping:
        # A further signal while the first one's clean-up runs (two Ctrl-C's at once, or one
        # landing in the import system that ends the command at once): ending here would leave
        # that clean-up half-done, a staging folder half-removed. It finishes, then ends.
        return
    _stopping = True
    # Looked up, not imported: nothing is staged before the module that stages is imported, and
    # a signal that lands while the main thread imports it would meet it half-made.
    staging = sys.modules.get("reconstruct.pipeline.staging")
    abandon_runs = getattr(staging, "abandon_runs", None)
    if abandon_runs is not None:
        abandon_runs()
    if signum == signal.SIGINT:
        os._exit(interrupted())
    sys.stderr.write("reconstruct: stopped (SIGTERM); output folders keep their earlier results\n")
    sys.stderr.flush()
    os._exit(EXIT_TERMINATED)


def _interrupt(signum: int, frame) -> None:
    """The first Ctrl-C: Python's own (a KeyboardInterrupt, so that each run removes what it
    staged on its way out, and a batch stops its cluster). A second one, while that clean-up
    waits for the files being written, ends the command at once (:func:`_terminate`).

    Not where the import system's own code runs: it takes the global import lock before its
    ``try`` blocks (in ``_get_module_lock`` and in a module lock's weakref callback), so an
    exception raised there can leave the lock held for good, and the clean-up then waits
    forever for a thread that imports. The command ends at once there, as on a second Ctrl-C.
    """
    signal.signal(signal.SIGINT, _terminate)
    if frame is not None and frame.f_code.co_filename.startswith("<frozen importlib"):
        _terminate(signum, frame)
    signal.default_int_handler(signum, frame)


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextmanager
def handlers() -> Iterator[None]:
    """SIGTERM ends the command at once (:func:`_terminate`); Ctrl-C unwinds it, a second one
    ends it (:func:`_interrupt`). Handlers can only be set in the main thread: elsewhere (a
    caller's thread) the caller's stay. Inside another ``handlers()`` (the entry point's around
    ``main``'s), Ctrl-C's are already the command's and stay as they are."""
    if not _in_main_thread():
        yield
        return
    previous = {signal.SIGTERM: signal.signal(signal.SIGTERM, _terminate)}
    hook = sys.unraisablehook

    def interrupt_lost(unraisable) -> None:
        # A Ctrl-C that came while a finaliser ran (a weakref callback, a __del__) is not
        # raised: Python prints it as "Exception ignored", with a traceback, and goes on. The
        # command ends at once instead, as on a second Ctrl-C. (Delivering the signal again a
        # moment later, from a thread, lost the next Ctrl-C when it landed in this hook, and a
        # finaliser of the import system can have left its lock held: see _interrupt.)
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            _terminate(signal.SIGINT, None)
        hook(unraisable)

    # Only where Ctrl-C raises KeyboardInterrupt: a caller that ignores it keeps that.
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, _interrupt)
        sys.unraisablehook = interrupt_lost
    try:
        yield
    finally:
        sys.unraisablehook = hook
        for signum, handler in previous.items():
            signal.signal(signum, handler)
