"""The project's error type for bad input.

Every problem a user can cause (a missing file, a malformed ``.lp``, mismatched image sizes,
an unwritable output folder) is raised as :class:`InputError`. The command line turns it into
one line on stderr and exit status 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import BinaryIO


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


def read_input_file(path: str | os.PathLike, what: str) -> bytes:
    """The bytes of a user's file, or an :class:`InputError` that says why not.

    ``what`` names the kind of file in the message ("PTM file", "RTI file", ...).
    """
    with open_input_file(path, what) as f:
        try:
            return f.read()
        except OSError as exc:
            raise InputError(f"cannot read {what} ({exc.strerror or exc})", path) from None


def open_input_file(path: str | os.PathLike, what: str) -> BinaryIO:
    """A user's file open for reading in binary, or an :class:`InputError` that says why not
    (see :func:`read_input_file`)."""
    try:
        return open(path, "rb")
    except FileNotFoundError:
        raise InputError(f"{what} not found", path) from None
    except IsADirectoryError:
        raise InputError(f"is a folder, not a {what}", path) from None
    except OSError as exc:
        raise InputError(f"cannot read {what} ({exc.strerror or exc})", path) from None


def read_input_text(path: str | os.PathLike, what: str) -> str:
    """The text of a user's file (UTF-8, a byte-order mark dropped, undecodable bytes
    replaced), or an :class:`InputError` that says why not; see :func:`read_input_file`."""
    return read_input_file(path, what).decode("utf-8-sig", errors="replace")


def first_few(items: Sequence[str], limit: int = 3, sep: str = ", ") -> str:
    """The first ``limit`` of ``items`` for a message, and how many more: ``"a, b, c and 4 more"``."""
    shown = sep.join(items[:limit])
    return shown + (f" and {len(items) - limit} more" if len(items) > limit else "")
