"""Atomic file writing, as the project conventions require for every output file."""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from typing import BinaryIO


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[BinaryIO]:
    """Open a temporary file next to ``path`` for binary writing; move it into place on success.

    Parameters
    ----------
    path : str or os.PathLike
        The final file name. Its folder must exist.

    Yields
    ------
    BinaryIO
        The open temporary file. If the ``with`` block raises, the temporary file is removed
        and ``path`` is left untouched.
    """
    path = os.fspath(path)
    folder, name = os.path.split(path)
    # A hidden, unique name in the same folder keeps os.replace atomic (same file system),
    # and opening it normally (not mkstemp) keeps the user's umask permissions.
    tmp = os.path.join(folder, f".{name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "xb") as fh:
            yield fh
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file.
    data : bytes
        The complete file content.
    """
    with atomic_write(path) as fh:
        fh.write(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write UTF-8 ``text`` with ``\\n`` line ends to ``path`` atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file.
    text : str
        The complete file content.
    """
    write_bytes_atomic(path, text.encode("utf-8"))
