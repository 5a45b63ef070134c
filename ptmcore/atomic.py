"""Atomic file writes.

Every output of the project is written through :func:`atomic_write`: the data goes to a
temporary file in the destination folder and is moved over the destination with
:func:`os.replace` only once it is complete. A crash, a full disk or an exception half-way
through therefore never leaves a truncated mesh behind and never destroys an existing file.
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
from collections.abc import Iterator
from typing import IO

from ptmcore.errors import InputError

__all__ = ["atomic_write"]

_MODES = {"w", "wt", "wb"}


def _folder_problem(exc: OSError) -> str:
    """Describe, for a user, why a file cannot be created in a folder."""
    if isinstance(exc, FileNotFoundError):
        return "the output folder does not exist"
    if isinstance(exc, NotADirectoryError):
        return "the output folder is not a folder"
    if isinstance(exc, PermissionError) or exc.errno == errno.EROFS:
        return "the output folder is not writable"
    return f"cannot create a file in the output folder ({exc.strerror or exc})"


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike,
    mode: str = "wb",
    *,
    encoding: str | None = "utf-8",
    newline: str | None = "\n",
) -> Iterator[IO]:
    """Open a file for writing so that it appears complete or not at all.

    The data are written to a hidden temporary file next to `path`; when the ``with`` block
    ends without an exception the temporary file is flushed to disk and renamed to `path`
    with :func:`os.replace` (atomic on POSIX and Windows). On an exception the temporary
    file is deleted and an existing `path` is left untouched.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file. Its folder must exist.
    mode : {"wb", "w", "wt"}
        Binary or text mode.
    encoding : str or None
        Text encoding (text mode only).
    newline : str or None
        Newline translation (text mode only); ``"\\n"`` writes the same bytes on every
        platform.

    Yields
    ------
    IO
        The open temporary file.

    Raises
    ------
    InputError
        If the folder does not exist or no file can be created in it, or if `path` cannot
        be replaced (for example because it is a folder).
    ValueError
        If `mode` is not a write mode.
    """
    if mode not in _MODES:
        raise ValueError(f"atomic_write mode must be one of {sorted(_MODES)}, not {mode!r}")
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    base = os.path.basename(path)

    # open(..., "x") creates the file exclusively with the usual permissions from the umask
    # (tempfile.mkstemp would force 0o600) and gives a named handle, which writers such as
    # tifffile need.
    text_kwargs = {} if "b" in mode else {"encoding": encoding, "newline": newline}
    while True:
        tmp = os.path.join(folder, f".{base}.{secrets.token_hex(4)}.tmp")
        try:
            handle = open(tmp, mode.replace("w", "x"), **text_kwargs)
            break
        except FileExistsError:
            continue
        except OSError as exc:
            raise InputError(_folder_problem(exc), folder) from exc

    try:
        with handle:
            yield handle
            handle.flush()
            # Without fsync a power cut right after os.replace can leave an empty file
            # under the final name on some file systems (ext4 delayed allocation).
            os.fsync(handle.fileno())
        try:
            os.replace(tmp, path)
        except IsADirectoryError as exc:
            raise InputError("is a folder; cannot write a file there", path) from exc
        except PermissionError as exc:
            raise InputError("cannot be replaced (permission denied)", path) from exc
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
