"""Atomic file writes.

Every output of the project is written through :func:`atomic_write`: the data goes to a
temporary file in the destination folder and is moved over the destination with
:func:`os.replace` only once it is complete. A crash, a full disk or an exception half-way
through therefore never leaves a truncated mesh behind and never destroys an existing file; a
full disk, a quota, a read-only or failing disk is one :class:`InputError` naming the file.

An output named through a symbolic link is written where the link points, and the link stays
(:func:`resolve_output`). Hidden names made beside an output (the temporary file here, the
staging folders of :mod:`reconstruct.pipeline.staging`) come from :func:`hidden_name`, which
shortens a long name so that they fit a file system's limit on a name's bytes.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import secrets
from collections.abc import Iterator
from typing import IO

from ptmcore.errors import InputError

__all__ = ["atomic_write", "hidden_name", "name_max", "resolve_output", "storage_problem"]

_MODES = {"w", "wt", "wb"}
#: The bytes of a file name where the system cannot tell (ext4, XFS, Btrfs, tmpfs: 255).
NAME_MAX = 255
#: Failures of the disk, not of the program: full, over quota, over a file size limit,
#: read-only, or failing. Raised by a write, a flush, ``fsync`` or the final rename.
_STORAGE_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO})
#: The bytes :func:`atomic_write` adds to a file's name for its temporary file: ``.{8 hex}.tmp``.
_TMP_SUFFIX_BYTES = 13


def storage_problem(exc: OSError) -> str | None:
    """The failure of the disk ``exc`` reports ("no space left on device", "disk quota
    exceeded", ...), or None when it is not one."""
    if exc.errno not in _STORAGE_ERRORS:
        return None
    return os.strerror(exc.errno).lower()


def name_max(folder: str | os.PathLike) -> int:
    """The longest file name, in bytes, the file system holding ``folder`` (or its nearest
    existing parent) allows."""
    folder = os.path.abspath(folder)
    while not os.path.isdir(folder) and os.path.dirname(folder) != folder:
        folder = os.path.dirname(folder)
    try:
        return os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):  # no pathconf (Windows), or no answer
        return NAME_MAX


def hidden_name(name: str, suffix_bytes: int, limit: int = NAME_MAX) -> str:
    """A hidden name made from ``name`` (``.NAME``) to which ``suffix_bytes`` more bytes can be
    added within ``limit`` bytes.

    A name too long for that is cut, at a character, and ends with ``~`` and 12 hexadecimal
    digits of its SHA-256 hash, so that two long names that begin alike get different hidden
    names, and the same name always the same one.
    """
    hidden = "." + name
    if len(os.fsencode(hidden)) + suffix_bytes <= limit:
        return hidden
    tag = "~" + hashlib.sha256(os.fsencode(name)).hexdigest()[:12]
    room = limit - suffix_bytes - len(tag)
    while len(os.fsencode(hidden)) > room:
        hidden = hidden[:-1]
    return hidden + tag


def resolve_output(path: str | os.PathLike, *, folder: bool = False) -> str:
    """The real path an output named ``path`` goes to: every symbolic link on the way followed,
    so that a link to a folder or a file keeps pointing at the result; or an
    :class:`InputError` for a name no output can have.

    Refused: a symbolic link that loops, or whose target does not exist (writing would turn
    the link into a file or folder of its own, or create its target somewhere unseen); a name
    longer than its file system allows; a file whose folder does not exist, or that is a
    folder; with ``folder``, an existing file that is not a folder, or a mount point (a result
    replaces its folder by a rename, which a mount point cannot take).
    """
    if not os.fspath(path):
        raise InputError("the output is an empty path; give a name with -o")
    if "\0" in os.fsdecode(path):
        raise InputError("is not a usable output path (a NUL character in the name)", path)
    path = os.path.abspath(path)
    # Before the links are followed: an existing link's target has names that fit.
    limit = name_max(os.path.dirname(path))
    longest = max(len(os.fsencode(part)) for part in path.split(os.sep))
    if longest > limit:
        raise InputError(f"holds a name of {longest} bytes, more than the {limit} this file system allows; "
                         "choose a shorter name", path)
    try:
        real = os.path.realpath(path, strict=True)
    except FileNotFoundError:
        real = os.path.realpath(path)  # a new output: nothing to resolve but its folders
        link = _dangling_link(path)
        if link is not None:
            raise InputError(f"is a symbolic link to {os.readlink(link)}, which does not exist; create it, or "
                             "remove the link", link) from None
    except NotADirectoryError:
        raise InputError("is a file, not a folder: cannot write the output folder inside it",
                         _first_file(path)) from None
    except OSError as exc:  # a folder that cannot be searched
        if exc.errno == errno.ELOOP:
            raise InputError("is a symbolic link that loops (too many levels of symbolic links)", path) from None
        raise InputError(f"is not a usable output path ({(exc.strerror or str(exc)).lower()})", path) from None
    if not folder:
        parent = os.path.dirname(real)
        if not os.path.isdir(parent):
            raise InputError("the output folder does not exist" if not os.path.lexists(parent)
                             else "the output folder is not a folder", parent)
        if os.path.isdir(real):
            raise InputError("is a folder; cannot write a file there", path)
    elif os.path.lexists(real):
        if not os.path.isdir(real):
            raise InputError("output path exists and is not a folder", path)
        if os.path.ismount(real):
            raise InputError("is a mount point: a new result replaces its folder, which a mount point cannot be; "
                             "give a folder inside it", path)
    return real


def _dangling_link(path: str) -> str | None:
    """The first component of ``path`` that is a symbolic link to nothing, if any."""
    parts = path.split(os.sep)
    for i in range(2, len(parts) + 1):
        part = os.sep.join(parts[:i])
        if os.path.islink(part) and not os.path.exists(part):
            return part
        if not os.path.lexists(part):
            return None
    return None


def _first_file(path: str) -> str:
    """The first of ``path``'s folders that is not a folder."""
    parent = os.path.dirname(path)
    while not os.path.isdir(os.path.dirname(parent)):
        parent = os.path.dirname(parent)
    return parent


def _folder_problem(exc: OSError) -> str:
    """Describe, for a user, why a file cannot be created in a folder."""
    if isinstance(exc, FileNotFoundError):
        return "the output folder does not exist"
    if isinstance(exc, NotADirectoryError):
        return "the output folder is not a folder"
    if isinstance(exc, PermissionError) or exc.errno == errno.EROFS:
        return "the output folder is not writable"
    return f"cannot create a file in the output folder ({(exc.strerror or str(exc)).lower()})"


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
        Destination file. Its folder must exist. A symbolic link is followed: the file it
        points to is replaced, and the link stays.
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
        If `path` cannot be an output (:func:`resolve_output`), no file can be created in its
        folder, the disk fails the write (full, over a quota or a file size limit, read-only,
        an I/O error), or `path` cannot be replaced (for example because it is a folder).
    ValueError
        If `mode` is not a write mode.
    """
    if mode not in _MODES:
        raise ValueError(f"atomic_write mode must be one of {sorted(_MODES)}, not {mode!r}")
    shown = os.fspath(path)
    path = resolve_output(path)
    folder, base = os.path.split(path)
    stem = hidden_name(base, _TMP_SUFFIX_BYTES, name_max(folder))

    # open(..., "x") creates the file exclusively with the usual permissions from the umask
    # (tempfile.mkstemp would force 0o600) and gives a named handle, which writers such as
    # tifffile need.
    text_kwargs = {} if "b" in mode else {"encoding": encoding, "newline": newline}
    while True:
        tmp = os.path.join(folder, f"{stem}.{secrets.token_hex(4)}.tmp")
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
            raise InputError("is a folder; cannot write a file there", shown) from exc
        except PermissionError as exc:
            raise InputError("cannot be replaced (permission denied)", shown) from exc
    except BaseException as exc:
        problem = _storage_failure(exc, tmp) if isinstance(exc, OSError) else None
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if problem is not None:
            raise InputError(f"cannot be written ({problem})", shown) from None
        raise


def _storage_failure(exc: OSError, tmp: str) -> str | None:
    """The failure of the disk behind ``exc``, raised while writing ``tmp`` (see
    :func:`storage_problem`). A write cut short without a reason (NumPy's ``tofile``, under
    tifffile: "3072 requested and 936 written") is put to the disk again: a block appended
    to ``tmp`` fails with the reason."""
    if exc.errno is None:
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_APPEND)
            try:
                os.write(fd, bytes(1 << 16))
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError as again:
            exc = again
    return storage_problem(exc)
