"""Staged output: files are written into a hidden folder and moved into place at the end.

Every command that writes an output folder (``run``, ``compare``, ``integrate``) does it
through :func:`staged_output`, so a run that fails leaves the earlier results untouched and
nothing half-written. The staging folder's name is unique (``.partial-`` and random letters),
so two runs in one process (threads, a Dask worker) or in two processes never share it.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from ptmcore.errors import InputError

__all__ = ["StagedOutput", "staged_output"]

STAGING_PREFIX = ".partial-"


@dataclass
class StagedOutput:
    """An output folder being written: files go to :attr:`staging`, then :meth:`publish`.

    Attributes
    ----------
    output : Path
        The folder the files end up in.
    staging : Path
        The hidden folder inside ``output`` that they are written to first.
    files : dict
        Each published file's name (relative to ``output``) and final path.
    """

    output: Path
    staging: Path
    files: dict[str, Path] = field(default_factory=dict)

    def __truediv__(self, name: str) -> Path:
        """``staged / "mesh.ply"``: where to write a file that :meth:`publish` will move."""
        return self.staging / name

    def publish(self, names: Iterable[str]) -> dict[str, Path]:
        """Move the named files (relative paths; sub-folders allowed) into the output folder."""
        for name in names:
            (self.output / name).parent.mkdir(exist_ok=True)
            os.replace(self.staging / name, self.output / name)
            self.files[name] = self.output / name
        return self.files


@contextmanager
def staged_output(output: str | os.PathLike) -> Iterator[StagedOutput]:
    """Create ``output`` and a unique staging folder inside it; remove the staging folder on exit.

    Parameters
    ----------
    output : path
        The output folder; created if needed.

    Yields
    ------
    StagedOutput
        Write files to ``staged / name``, then call ``staged.publish(names)``; whatever is
        not published when the block ends (normally or by an exception) is deleted.

    Raises
    ------
    InputError
        If ``output`` exists and is not a folder, or cannot be written.
    """
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=out))
    except OSError as exc:
        raise InputError(f"cannot write the output folder ({exc.strerror})", out) from None
    try:
        yield StagedOutput(out, staging)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
