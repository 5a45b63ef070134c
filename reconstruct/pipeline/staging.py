"""Staged output: a result folder is the complete old result or the complete new one, always.

Every command that writes an output folder (``run``, ``compare``, ``integrate``) does it through
:func:`staged_output`. The new result is built in a hidden folder beside the output folder
(``.NAME.partial-`` and random letters, on the same file system) and put in place by one
directory rename: where the system can exchange two folders atomically (Linux's
``renameat2(RENAME_EXCHANGE)``) the old and new results swap in one step, elsewhere the old one
is renamed aside (``.NAME.old-…``) just before the new one takes its name. Whatever is killed
when, the output folder never mixes files of two runs; a run killed between the two renames of
the fallback leaves the old result aside, and the next run on that folder puts it back.

One run at a time per folder: :func:`staged_output` holds an exclusive lock
(``.NAME.lock`` beside the folder, ``flock``, released by the system when the process dies), and
a second run refuses with a message naming the first one's process. Holding it, a run removes
what dead runs left beside the folder. A folder that exists must be empty or hold only the
files results hold, in its sub-folders too: a folder with any other file (the user's notes, the
photographs) is never replaced. A run that fails leaves nothing new behind, not even the folders
it created to hold the output.

The output folder is checked before anything else (:func:`ptmcore.atomic.resolve_output`): a
symbolic link is followed once, so the result goes where it points and the link stays; a link
to nothing or that loops, a mount point, a name too long are refused. A name so long that the
hidden names would not fit the file system's limit (255 bytes) is cut in them and ends with a
hash of the whole (:func:`ptmcore.atomic.hidden_name`). The disk failing (full, over quota,
read-only) is an :class:`InputError` naming the file of the output folder being written.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fnmatch
import glob
import os
import secrets
import shutil
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from ptmcore.atomic import hidden_name, name_max, resolve_output, storage_problem
from ptmcore.errors import InputError, first_few

__all__ = ["StagedOutput", "abandon_runs", "staged_output"]

#: The user's own files inside a result: figures, profiles and distances saved from the preview
#: window (``reconstruct.viewer``). Every new result of the folder carries them over.
CARRIED = ("preview",)
#: Hidden names beside an output folder ``NAME``: ``.NAME.partial-…`` (a result being built),
#: ``.NAME.old-…`` (an old result renamed aside for a moment), ``.NAME.lock``.
STAGING_PREFIX = ".partial-"
_OLD_PREFIX = ".old-"
_LOCK_SUFFIX = ".lock"
#: The most bytes a hidden name adds to ``.NAME``: a staging folder's, as
#: :func:`abandon_runs` renames it (``.partial-`` and 8 hexadecimal digits, ``.abandoned``).
_ADDED_BYTES = len(STAGING_PREFIX) + 8 + len(".abandoned")
#: The names a result folder holds (README, "Output folder"; ``compare``'s files): only a folder
#: of these alone (or an empty one) is replaced by a new result. Later versions add names here,
#: never rename them, as the README promises of the files.
_OUTPUT_NAMES = ("coefficients.ptm", "coefficients.rti", "web", "solid.stl", "mesh.glb", "normals.npy",
                 "normals.png", "albedo.png", "height.tif", "mesh.ply", "mesh.obj", "mesh.mtl",
                 "mesh_texture.png", "mask.png", "loo_*.tif", "light_positions.csv", "lights.lp", "report.json",
                 "report.html", "comparison.json", "distances.ply", "histogram.png", "overlay.png", *CARRIED)
#: What the folders among them hold (README: ``web/``). Any other folder of a result holds
#: nothing; :data:`CARRIED` ones are the user's and hold anything.
_FOLDER_NAMES = {"web": ("index.html", "viewer.json", "normals.png", "height.png", "info.json", "plane_*.jpg")}


#: The staging folders and lock files of this process's runs in progress, for
#: :func:`abandon_runs` alone: a signal handler cannot reach them through the call stack.
_LIVE: set[Path] = set()


def abandon_runs() -> None:
    """Remove the staging folders and lock files of every run in progress in this process,
    leaving each output folder as it is (for a SIGTERM handler that then ends the process:
    a result is only ever changed by one rename, so stopping anywhere else loses nothing)."""
    for path in list(_LIVE):
        if path.is_dir() and not path.is_symlink():
            # Renamed first: the run's other threads, still writing, can no longer create files
            # in it by its name while it is being removed.
            gone = path.with_name(path.name + ".abandoned")
            with contextlib.suppress(OSError):
                os.rename(path, gone)
                path = gone
            shutil.rmtree(path, ignore_errors=True)
            shutil.rmtree(path, ignore_errors=True)  # what a thread made during the first pass
        else:
            with contextlib.suppress(OSError):
                path.unlink()


def _hidden_stem(output: Path) -> str:
    """``.NAME`` for ``output``, cut and hashed if needed so that every hidden name made from
    it fits the file system's limit."""
    return hidden_name(output.name, _ADDED_BYTES, name_max(output.parent))


def staging_names(output: Path) -> tuple[str, str]:
    """The prefixes of the hidden folders beside ``output``: being built, renamed aside."""
    stem = _hidden_stem(output)
    return f"{stem}{STAGING_PREFIX}", f"{stem}{_OLD_PREFIX}"


@dataclass
class StagedOutput:
    """An output folder being written: files go to :attr:`staging`, then :meth:`publish`.

    Attributes
    ----------
    output : Path
        The folder the result ends up as.
    staging : Path
        The hidden folder beside ``output`` that the files are written to first.
    files : dict
        Each published file's name (relative to ``output``) and final path.
    """

    output: Path
    staging: Path
    files: dict[str, Path] = field(default_factory=dict)

    def __truediv__(self, name: str) -> Path:
        """``staged / "mesh.ply"``: where to write a file that :meth:`publish` will put in place."""
        return self.staging / name

    def keep_existing(self, exclude: Iterable[str] = ()) -> list[str]:
        """Carry the output folder's current files (all but ``exclude``, top-level names) over
        into the staging folder, as hard links where the file system allows (copies
        elsewhere), for a result that adds to an earlier one (a comparison written beside its
        reconstruction). Returns their names, to publish with the new files."""
        if not self.output.is_dir():
            return []
        skip = set(exclude)
        kept = []
        for entry in sorted(self.output.iterdir()):
            if entry.name not in skip:
                with _disk_errors(entry):
                    _carry(entry, self.staging / entry.name)
                kept.append(entry.name)
        return kept

    def publish(self, names: Iterable[str]) -> dict[str, Path]:
        """Make the named files (relative paths; sub-folders allowed) the output folder's whole
        content, in one step: anything else in the staging folder (scratch files) is removed
        first, then the staging folder takes the output folder's place. Once only. The
        folders of :data:`CARRIED` (the user's saved figures) come over from the old result."""
        if self.files:
            raise RuntimeError(f"{self.output} was already published")
        keep = {Path(name) for name in names}
        if self.output.is_dir():  # the user's figures live on in the new result
            for name in CARRIED:
                if (self.output / name).is_dir() and not (self.staging / name).exists():
                    with _disk_errors(self.output / name):
                        _carry(self.output / name, self.staging / name)
                    keep.add(Path(name))
        missing = [str(n) for n in keep if not (self.staging / n).exists()]
        if missing:
            raise FileNotFoundError(f"not written, cannot publish: {', '.join(sorted(missing))}")
        _prune(self.staging, keep)
        with _disk_errors(self.output):
            _swap_in(self.staging, self.output)
        self.files = {str(n): self.output / n for n in sorted(keep, key=str)}
        return self.files


@contextmanager
def _disk_errors(path: Path) -> Iterator[None]:
    """The disk failing while the result is put in place (full, read-only; a folder that
    cannot be renamed) as an :class:`InputError` naming ``path``."""
    try:
        yield
    except OSError as exc:
        reason = storage_problem(exc) or (exc.strerror or str(exc)).lower()
        raise InputError(f"cannot put the new result in place ({reason}); the folder keeps its earlier result",
                         path) from None


def _carry(src: Path, dst: Path) -> None:
    """A file or folder of the old result carried into the new one, by hard links."""
    if src.is_dir() and not src.is_symlink():
        shutil.copytree(src, dst, copy_function=_link_or_copy, symlinks=True)
    else:
        _link_or_copy(src, dst)


def _link_or_copy(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Hard-link ``src`` as ``dst`` (no copy of a large mesh), or copy it where links fail."""
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        shutil.copy2(src, dst, follow_symlinks=False)


def _prune(root: Path, keep: set[Path]) -> None:
    """Remove from ``root`` everything that is neither in ``keep`` nor a folder leading to it."""
    parents = {p for n in keep for p in n.parents}
    for path in sorted(root.rglob("*"), key=lambda p: len(p.parts), reverse=True):
        rel = path.relative_to(root)
        if rel in keep or rel in parents:
            continue
        if any(k in rel.parents for k in keep):  # inside a published folder
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two folders in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the
    system or the file system cannot."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _swap_in(staging: Path, output: Path) -> None:
    """Put ``staging`` in place of ``output``; the old result ends up at ``staging``'s name
    (removed by :func:`staged_output`) or, in the two-rename fallback, is removed here."""
    if not output.exists():
        os.rename(staging, output)
        return
    if _exchange(staging, output):
        return
    aside = _unique_folder(output.parent, staging_names(output)[1])
    os.rename(output, aside / "result")  # a kill from here …
    try:
        os.rename(staging, output)  # … to here leaves the old result aside: the next run restores it
    except OSError:
        os.rename(aside / "result", output)
        raise
    shutil.rmtree(aside, ignore_errors=True)


def _foreign(folder: Path) -> list[str]:
    """The files and folders in ``folder``'s tree that no result holds (:data:`_OUTPUT_NAMES`,
    and in their folders :data:`_FOLDER_NAMES`), relative to it: a folder with any is not
    replaced, since they would go with the old result and might be anything of the user's
    (notes put beside a result or in its ``web/``, the photographs themselves)."""
    foreign = []
    for entry in sorted(folder.iterdir()):
        if not _named_like(entry.name, _OUTPUT_NAMES):
            foreign.append(entry.name)
        elif entry.name not in CARRIED and entry.is_dir() and not entry.is_symlink():
            inside = _FOLDER_NAMES.get(entry.name, ())
            # A result's folders hold files only: a folder in them is the user's.
            foreign += [f"{entry.name}/{p.name}" for p in sorted(entry.iterdir())
                        if not _named_like(p.name, inside) or (p.is_dir() and not p.is_symlink())]
    return foreign


def _named_like(name: str, patterns: Iterable[str]) -> bool:
    return any(fnmatch.fnmatchcase(name, pattern) for pattern in patterns)


def _recover(output: Path) -> None:
    """Undo what dead runs left beside ``output`` (called with its lock held): an old result
    renamed aside comes back when ``output`` is missing; everything else goes."""
    building, aside = staging_names(output)
    stale = sorted(output.parent.glob(glob.escape(aside) + "*"), key=lambda p: p.stat().st_mtime)
    if not output.exists() and not output.is_symlink():
        for folder in reversed(stale):
            if (folder / "result").is_dir():
                os.rename(folder / "result", output)
                break
    for leftover in [*stale, *output.parent.glob(glob.escape(building) + "*")]:
        shutil.rmtree(leftover, ignore_errors=True)
    if output.is_dir():  # staging folders of earlier versions, inside the result
        for leftover in output.glob(STAGING_PREFIX + "*"):
            shutil.rmtree(leftover, ignore_errors=True)


@contextmanager
def _folder_lock(output: Path) -> Iterator[None]:
    """Hold ``.NAME.lock`` beside ``output`` exclusively, or raise :class:`InputError` naming
    the process that holds it. Without ``fcntl`` (Windows) runs are not locked."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    path = output.parent / f"{_hidden_stem(output)}{_LOCK_SUFFIX}"
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise InputError(f"cannot write the output folder ({exc.strerror})", output) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip()
            os.close(fd)
            raise InputError(
                f"another reconstruct run{f' (process {holder})' if holder else ''} is writing this folder; "
                "wait for it to finish or choose another output folder", output) from None
        # The holder before us may have removed the file between our open and our lock.
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    _LIVE.add(path)
    try:
        with contextlib.suppress(OSError):  # a full disk: the process is only named in a message
            os.ftruncate(fd, 0)
            os.write(fd, str(os.getpid()).encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)  # before the unlock, so a waiting run sees it gone and retries
        _LIVE.discard(path)
        os.close(fd)


def _unique_folder(parent: Path, prefix: str, live: bool = False) -> Path:
    """A new folder ``parent/prefix…`` with the permissions of any new folder (the umask's;
    ``tempfile.mkdtemp`` would make it, and so the published result, private). ``live``: it
    is in :data:`_LIVE` from before it exists, so a SIGTERM at any moment finds it."""
    while True:
        path = parent / (prefix + secrets.token_hex(4))
        if live:
            _LIVE.add(path)
        try:
            path.mkdir()
            return path
        except FileExistsError:
            _LIVE.discard(path)
            continue
        except BaseException:
            _LIVE.discard(path)
            raise


def _make_folder(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; return those created, outermost first."""
    created = []
    for p in [*reversed(folder.parents), folder]:
        if not p.exists():
            p.mkdir()
            created.append(p)
    return created


def _in_output(exc: InputError, staging: Path, output: Path) -> InputError:
    """``exc`` naming the output folder's file where it named the staging folder's: the user
    knows the one, and the other is gone when the message is read."""
    if exc.path is None or not Path(exc.path).is_relative_to(staging):
        return exc
    return InputError(exc.problem, output / Path(exc.path).relative_to(staging))


@contextmanager
def staged_output(output: str | os.PathLike) -> Iterator[StagedOutput]:
    """Lock ``output``, build the new result in a staging folder beside it, and remove the
    staging folder on exit (with the old result in it once :meth:`StagedOutput.publish` has
    swapped them).

    Parameters
    ----------
    output : path
        The output folder. Its parent folders are created if needed (and removed again if the
        run fails); it is created by the publication itself.

    Yields
    ------
    StagedOutput
        Write files to ``staged / name``, then call ``staged.publish(names)``; when the block
        ends without a publication (an exception), the output folder is as it was.

    Raises
    ------
    InputError
        If ``output`` cannot be an output folder (:func:`ptmcore.atomic.resolve_output`: empty,
        a file, a link to nothing, a mount point, a name too long), holds files that are not an
        earlier result, is being written by another run, or its parent cannot be written; or if
        the disk fails a write (named as the output folder's file, not the staging folder's).
    """
    out = Path(resolve_output(output, folder=True))
    created: list[Path] = []
    try:
        try:
            created = _make_folder(out.parent)
        except OSError as exc:
            raise InputError(f"cannot write the output folder ({exc.strerror})", output) from None
        with _folder_lock(out):
            try:
                _recover(out)
                foreign = _foreign(out) if out.is_dir() else []
            except OSError as exc:  # a folder of it that cannot be read
                raise InputError(f"cannot read the output folder ({(exc.strerror or str(exc)).lower()})",
                                 exc.filename or output) from None
            if foreign:
                raise InputError(f"the output folder is not a reconstruct result: it holds {first_few(foreign)}, "
                                 "which a new result would replace; move them, or choose a new or empty folder",
                                 output)
            try:
                staging = _unique_folder(out.parent, staging_names(out)[0], live=True)
            except OSError as exc:
                raise InputError(f"cannot write the output folder ({exc.strerror})", output) from None
            staged = StagedOutput(out, staging)
            try:
                yield staged
            except InputError as exc:
                named = _in_output(exc, staging, out)
                if named is exc:
                    raise
                raise named from None
            finally:
                shutil.rmtree(staging, ignore_errors=True)
                _LIVE.discard(staging)
    except BaseException:
        for folder in reversed(created):
            with contextlib.suppress(OSError):
                folder.rmdir()  # only if still empty
        raise
