"""Captures as archives keep them: RTIBuilder projects, and photographs that are not where the
light file says.

RTIBuilder (Cultural Heritage Imaging), the field's builder for fifteen years, keeps a capture
in a project folder::

    project/
        original-captures/   the camera's files
        jpeg-exports/        the photographs it processed
        assembly-files/      its light file, project.lp (and its XML), listing each photograph
                             by the absolute path it had on the machine that built it
                             (C:\\Users\\…\\jpeg-exports\\IMG_0001.jpg)
        finished-files/      its .ptm and .rti

:func:`project_lp` finds such a project's light file, so that ``run`` and ``batch`` take the
project folder itself. :func:`locate_photographs` finds the photographs of a light file that
are not where it says (the light file in ``assembly-files/``, moved to another machine, or
given with ``--lp`` from elsewhere): in the capture folder first, then where the light file
puts them, then in the project folder its paths name and in ``jpeg-exports/`` beside the
light file's folder. The first folder that holds every photograph is taken; a photograph
found nowhere is named with the folders looked in.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path, PurePosixPath, PureWindowsPath

from ptmcore.errors import InputError, first_few
from ptmcore.lp import LightSet

__all__ = ["ASSEMBLY_FOLDER", "PHOTOGRAPH_FOLDER", "locate_photographs", "project_lp"]

#: The project's folder holding its light file.
ASSEMBLY_FOLDER = "assembly-files"
#: The project's folder holding the photographs it processed.
PHOTOGRAPH_FOLDER = "jpeg-exports"


def project_lp(folder: Path) -> Path | None:
    """The light file of an RTIBuilder project folder (the ``.lp`` file in its
    ``assembly-files/``), or None when ``folder`` is not one.

    Raises
    ------
    InputError
        When ``assembly-files/`` holds several ``.lp`` files (naming them: choose one with ``--lp``).
    """
    assembly = Path(folder) / ASSEMBLY_FOLDER
    if not assembly.is_dir():
        return None
    found = sorted(p for p in assembly.iterdir() if p.suffix.lower() == ".lp")
    if len(found) > 1:
        raise InputError(f"several .lp files in its {ASSEMBLY_FOLDER}/ ({first_few([p.name for p in found])}); "
                         "choose one with --lp", folder)
    return found[0] if found else None


def _named_folder(names: tuple[str, ...]) -> str | None:
    """The folder name the light file's paths share (``jpeg-exports`` for RTIBuilder's), if any."""
    parents = {(PureWindowsPath(n) if ("\\" in n or PureWindowsPath(n).drive) else PurePosixPath(n)).parent.name
               for n in names}
    return parents.pop() if len(parents) == 1 and "" not in parents else None


def locate_photographs(lights: LightSet, capture: Path | None = None) -> LightSet:
    """``lights`` with each photograph found on this machine.

    Parameters
    ----------
    lights : LightSet
        Read from a light file (:func:`ptmcore.lp.read_lp`): its ``paths`` where the file puts
        them, ``names`` as it writes them.
    capture : Path, optional
        The capture folder the user gave (looked in first; a file's folder counts).

    Returns
    -------
    LightSet
        The same lights, with paths into the first folder holding every photograph by name:
        ``capture``, then where the light file puts them (unchanged when they are all there),
        then, beside the light file's folder, the folder its paths name and
        :data:`PHOTOGRAPH_FOLDER`.

    Raises
    ------
    InputError
        Naming the first photograph found in none of them, and where it was looked for.
    """
    names = [p.name for p in lights.paths]
    first = None if capture is None else (Path(capture) if Path(capture).is_dir() else Path(capture).parent)
    if first is not None and _holds(first, names):
        return _moved(lights, first, names)
    if all(p.is_file() for p in lights.paths):
        return lights
    project = [] if lights.source is None else [
        lights.source.parent.parent / f for f in (_named_folder(lights.names), PHOTOGRAPH_FOLDER) if f]
    for folder in dict.fromkeys(project):  # in order, once each
        if folder != first and _holds(folder, names):
            return _moved(lights, folder, names)
    missing = next((p for p in lights.paths if not _exists(p)), None)
    if missing is None:  # all there, some not regular files: decoding says what they are
        return lights
    looked = [str(f) for f in dict.fromkeys([missing.parent, *([first] if first else []), *project])]
    raise InputError(f"photograph {missing.name} not found; looked in {first_few(looked, 4)}",
                     lights.source or missing)


def _moved(lights: LightSet, folder: Path, names: list[str]) -> LightSet:
    """``lights`` with every photograph in ``folder`` (the same object when they are there)."""
    paths = [folder / n for n in names]
    return lights if paths == list(lights.paths) else dataclasses.replace(lights, paths=paths)


def _exists(path: Path) -> bool:
    try:
        return path.exists() or path.is_symlink()  # a broken link is there, and said to be broken
    except OSError:
        return False


def _holds(folder: Path, names: list[str]) -> bool:
    """Whether ``folder`` holds a regular file of every name."""
    try:
        return folder.is_dir() and all((folder / n).is_file() for n in names)
    except OSError:  # a name too long for the file system
        return False
