"""The installed ``reconstruct`` command (and ``python -m reconstruct``): the entry point.

Apart from :mod:`reconstruct.cli.main` so that importing it imports nothing heavy: the
command's own imports (NumPy, numba, a tenth of a second or more) happen inside
:func:`console`, where a Ctrl-C ends the command as it does during a run (one line, status
130), not with a traceback. (Only in the interpreter's own start, the first few hundredths of
a second, does Python print one.)
"""

from __future__ import annotations

import os
import sys

from reconstruct.cli.signals import handlers, interrupted


def console() -> None:
    """Run :func:`reconstruct.cli.main.main`, then exit at once with its status.

    The interpreter's own teardown (VTK's and numba's objects, the memory a run freed) took a
    quarter of a second after every run, 4 % of a 6-megapixel run (benchmarks/speed.py). By
    then every result is published (output folders change by one rename) and every command has
    closed what it opened (files, windows, a batch's cluster); only the standard streams are
    left to flush. An exception that escapes ``main`` (a bug) still unwinds as usual.
    """
    with handlers():  # never left: os._exit ends the process inside (see reconstruct.cli.signals)
        try:
            from reconstruct.cli.main import main

            code = main()
            sys.stdout.flush()
            sys.stderr.flush()
        except KeyboardInterrupt:  # before main() handles it itself: nothing is staged yet
            code = interrupted()
        os._exit(code)
