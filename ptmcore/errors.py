"""The project's error type for bad input.

Every problem a user can cause (a missing file, a malformed ``.lp``, mismatched image sizes,
an unwritable output folder) is raised as :class:`InputError`. The command line turns it into
one line on stderr and exit status 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import os


class InputError(Exception):
    """Bad input that the user can fix.

    Parameters
    ----------
    problem : str
        What is wrong, in words a user understands.
    path : str or os.PathLike, optional
        The file or folder the problem is about; it leads the message.
    """

    def __init__(self, problem: str, path: str | os.PathLike | None = None) -> None:
        self.problem = problem
        self.path = None if path is None else os.fspath(path)
        super().__init__(f"{self.path}: {problem}" if self.path else problem)
