"""The project's error type for bad input.

Every problem a user can cause (a missing file, a malformed ``.lp``, mismatched image sizes,
an unwritable output folder) is raised as :class:`InputError`. The command line turns it into
one line on stderr and exit status 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import codecs
import os
import stat
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
        shown = _printable(os.fsdecode(self.path)) if self.path else None
        super().__init__(f"{shown}: {problem}" if shown else problem)


def _printable(name: str) -> str:
    """A file name as one printable line: control characters (a NUL, a newline, an escape
    sequence in a hostile name) shown as escapes, so the message stays one honest line."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in name)


def read_input_file(path: str | os.PathLike, what: str, max_bytes: int | None = None) -> bytes:
    """The bytes of a user's file, or an :class:`InputError` that says why not.

    ``what`` names the kind of file in the message ("PTM file", "RTI file", ...). Only a
    regular file is read (see :func:`open_input_file`); ``max_bytes``, when given, refuses a
    larger file before anything is read, so a stray multi-gigabyte file named like an input
    costs nothing.
    """
    with open_input_file(path, what) as f:
        size = os.fstat(f.fileno()).st_size
        if max_bytes is not None and size > max_bytes:
            raise InputError(f"the {what} is {size:,} bytes, more than the {max_bytes:,} this program "
                             "reads for it (not the file meant?)", path)
        try:
            # A regular file may still grow while it is read, or report size 0 (/proc):
            # never read past the bound.
            data = f.read() if max_bytes is None else f.read(max_bytes + 1)
        except OSError as exc:
            raise InputError(f"cannot read {what} ({exc.strerror or exc})", path) from None
    if max_bytes is not None and len(data) > max_bytes:
        raise InputError(f"the {what} is more than the {max_bytes:,} bytes this program reads for it", path)
    return data


def _kind(mode: int) -> str:
    if stat.S_ISFIFO(mode):
        return "a named pipe (FIFO)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def open_input_file(path: str | os.PathLike, what: str) -> BinaryIO:
    """A user's file open for reading in binary, or an :class:`InputError` that says why not
    (see :func:`read_input_file`).

    Only a regular file is opened. A named pipe, a device (``/dev/zero``) or a socket would
    block the run or feed it without end, so it is refused with one line; it is opened without
    blocking to find out what it is (opening a FIFO for reading otherwise waits for a writer).
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        if os.path.islink(path):
            raise InputError(f"is a symbolic link to {os.readlink(path)!r}, which does not exist", path) from None
        raise InputError(f"{what} not found", path) from None
    except IsADirectoryError:
        raise InputError(f"is a folder, not a {what}", path) from None
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the name
        raise InputError(f"cannot read {what} ({getattr(exc, 'strerror', None) or exc})", path) from None
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise InputError(f"is a folder, not a {what}", path)
        if not stat.S_ISREG(mode):
            raise InputError(f"is {_kind(mode)}, not a {what}", path)
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_input_text(path: str | os.PathLike, what: str, max_bytes: int | None = None) -> str:
    """The text of a user's file, or an :class:`InputError` that says why not; see
    :func:`read_input_file`.

    UTF-8, with or without a byte-order mark; UTF-16 and UTF-32 when their byte-order mark
    says so (Windows' Notepad saves "Unicode" as UTF-16). Undecodable bytes are replaced.
    """
    data = read_input_file(path, what, max_bytes)
    for bom, codec in ((codecs.BOM_UTF32_LE, "utf-32"), (codecs.BOM_UTF32_BE, "utf-32"),
                       (codecs.BOM_UTF16_LE, "utf-16"), (codecs.BOM_UTF16_BE, "utf-16")):
        if data.startswith(bom):
            return data.decode(codec, errors="replace")
    return data.decode("utf-8-sig", errors="replace")


def first_few(items: Sequence[str], limit: int = 3, sep: str = ", ") -> str:
    """The first ``limit`` of ``items`` for a message, and how many more: ``"a, b, c and 4 more"``."""
    shown = sep.join(items[:limit])
    return shown + (f" and {len(items) - limit} more" if len(items) > limit else "")
