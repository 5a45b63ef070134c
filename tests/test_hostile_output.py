"""Issue 36, output: a full or failing disk, hostile ``-o`` names (links, mount points, long
names) and the user's files inside a result are one line and exit status 2, the earlier result
kept and nothing half-written; a legal long name and a link to a folder work."""

from __future__ import annotations

import builtins
import errno
import fnmatch
import importlib
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import ptmcore.atomic as atomic
import reconstruct.pipeline.staging as staging
from data_synthetic import write_capture
from ptmcore.atomic import atomic_write
from ptmcore.errors import InputError
from reconstruct.pipeline import RunOptions, run_capture, staged_output

from helpers import run_cli

pytestmark = pytest.mark.skipif(os.name != "posix", reason="links, rlimits and NAME_MAX: POSIX")

#: The disk's failures a write can meet, and the words the message must hold.
#: The files of a result's web page (README, "Output folder"), and plane_*.jpg.
WEB_FILES = ("index.html", "viewer.json", "normals.png", "height.png", "info.json")
DISK_ERRORS = {errno.ENOSPC: "no space left on device", errno.EDQUOT: "disk quota exceeded",
               errno.EROFS: "read-only file system", errno.EIO: "input/output error"}
_SETTINGS = settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
#: Any name a file may have: up to 255 bytes, no "/" or NUL; of any length up to that.
_NAMES = (st.integers(1, 255)
          .flatmap(lambda k: st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="/\0"),
                                     min_size=k, max_size=k))
          .map(lambda n: n.encode()[:255].decode(errors="ignore")).filter(lambda n: n not in ("", ".", "..")))


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("hostile_output") / "capture"
    write_capture(folder, shape=(24, 32), n_lights=8, seed=5)
    return folder


@pytest.fixture(scope="module")
def result(capture, tmp_path_factory) -> Path:
    """A finished result, copied by the tests as the earlier result a run must keep."""
    return run_capture(capture, tmp_path_factory.mktemp("hostile_result") / "out", RunOptions(threads=1)).output


def _tree(folder: Path) -> dict[str, bytes | None]:
    """Every path below ``folder`` with its bytes (None for a folder)."""
    return {str(p.relative_to(folder)): None if p.is_dir() else p.read_bytes() for p in sorted(folder.rglob("*"))}


def _one_line(code: int, err: str, *needles: str) -> str:
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


class _FailingFile:
    """An open file whose writes fail as a full, over-quota, read-only or failing disk's do."""

    def __init__(self, handle, err: int) -> None:
        self._handle, self._err = handle, err

    def write(self, data) -> int:
        raise OSError(self._err, os.strerror(self._err))

    def __getattr__(self, name):
        return getattr(self._handle, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._handle.close()


def _disk_fails(monkeypatch, name: str, err: int = errno.ENOSPC) -> None:
    """Writes of the file ``name`` (atomic_write's temporary file for it) fail with ``err``."""

    def opener(path, mode, **kw):
        handle = builtins.open(path, mode, **kw)
        return _FailingFile(handle, err) if os.path.basename(path).startswith(f".{name}.") else handle

    monkeypatch.setattr(atomic, "open", opener, raising=False)


def _no_decoding(monkeypatch) -> None:
    """Make any decoding of the capture an error that is not one line: the output's checks
    must come first."""
    def decoded(*args, **kwargs):
        raise AssertionError("the capture was decoded before the output was checked")

    monkeypatch.setattr(importlib.import_module("reconstruct.pipeline.run"), "load_capture", decoded)


# ------------------------------------------------------------------------ a full or failing disk


def test_a_full_disk_in_a_run_is_one_line_naming_the_file_and_keeps_the_old_result(capture, result, tmp_path,
                                                                                     monkeypatch, capsys):
    out = tmp_path / "out"
    shutil.copytree(result, out)
    before = _tree(out)
    _disk_fails(monkeypatch, "mesh.ply")  # written by the run's file writer, in a thread
    code, _, err = run_cli(["run", capture, "-o", out, "-q", "--threads", "1"], capsys)
    _one_line(code, err, str(out / "mesh.ply"), "no space left on device")
    assert _tree(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging folder, no lock


@pytest.mark.parametrize("err", sorted(DISK_ERRORS))
def test_a_failing_disk_in_relight_is_one_line_and_keeps_the_old_image(result, tmp_path, monkeypatch, capsys, err):
    image = tmp_path / "relit.png"
    image.write_bytes(b"the earlier image")
    _disk_fails(monkeypatch, "relit.png", err)
    code, _, stderr = run_cli(["relight", result / "coefficients.ptm", "-o", image, "--light", "0,0,1"], capsys)
    _one_line(code, stderr, str(image), DISK_ERRORS[err])
    assert image.read_bytes() == b"the earlier image"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["relit.png"]


def test_integrate_on_a_full_disk_is_one_line(result, tmp_path, monkeypatch, capsys):
    _disk_fails(monkeypatch, "report.json", errno.EDQUOT)
    code, _, err = run_cli(["integrate", result / "normals.npy", "-o", tmp_path / "out", "-q"], capsys)
    _one_line(code, err, str(tmp_path / "out" / "report.json"), "disk quota exceeded")
    assert list(tmp_path.iterdir()) == []


def test_demo_on_a_full_disk_leaves_no_half_capture(tmp_path, monkeypatch, capsys):
    _disk_fails(monkeypatch, "img_003.tif")
    code, _, err = run_cli(["demo", "-o", tmp_path / "demo", "--size", "32x24", "--lights", "6"], capsys)
    _one_line(code, err, "img_003.tif", "no space left on device")
    assert list(tmp_path.iterdir()) == []


_CUT_SHORT = """
import resource, signal, sys
import numpy as np, tifffile
from ptmcore.atomic import atomic_write
from ptmcore.errors import InputError
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
try:
    with atomic_write(sys.argv[1]) as f:
        tifffile.imwrite(f, np.zeros((64, 64), np.float32))  # 16 KB through ndarray.tofile
except InputError as exc:
    print(exc.path, exc.problem, sep="|")
"""


def test_a_write_the_kernel_cuts_short_is_an_input_error(tmp_path):
    """Files may grow to 4096 bytes (the kernel's EFBIG, a real write failure wherever it
    happens: NumPy's ``tofile`` under tifffile reports none of its own). In a child process:
    the limit would cut the test runner's own output to a file short as well."""
    target = tmp_path / "height.tif"
    target.write_bytes(b"old")
    proc = subprocess.run([sys.executable, "-c", _CUT_SHORT, str(target)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    path, problem = proc.stdout.strip().split("|")
    assert path == str(target) and "file too large" in problem
    assert os.listdir(tmp_path) == ["height.tif"] and target.read_bytes() == b"old"


# ------------------------------------------------------------------------ hostile -o names


def test_a_dangling_link_as_output_is_refused_before_decoding(capture, tmp_path, monkeypatch, capsys):
    _no_decoding(monkeypatch)
    link = tmp_path / "out"
    link.symlink_to(tmp_path / "gone")
    code, _, err = run_cli(["run", capture, "-o", link, "-q"], capsys)
    _one_line(code, err, str(link), "does not exist")
    assert link.is_symlink() and sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_symlink_loop_as_output_is_refused_before_decoding(capture, tmp_path, monkeypatch, capsys):
    _no_decoding(monkeypatch)
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    for out in (tmp_path / "a", tmp_path / "a" / "out"):
        code, _, err = run_cli(["run", capture, "-o", out, "-q"], capsys)
        _one_line(code, err, "loop")
    # compare checks its folder before the scan is read; calibrate its .lp before the photographs
    code, _, err = run_cli(["compare", tmp_path / "no-result", tmp_path / "no-scan.ply", "-o", tmp_path / "a"], capsys)
    _one_line(code, err, "loop")
    code, _, err = run_cli(["calibrate", tmp_path / "no-capture", "-o", tmp_path / "a"], capsys)
    _one_line(code, err, "loop")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]


def test_a_mount_point_as_output_is_refused_before_decoding(capture, tmp_path, monkeypatch, capsys):
    _no_decoding(monkeypatch)
    mount = tmp_path / "usb"
    mount.mkdir()
    ismount = os.path.ismount
    monkeypatch.setattr(os.path, "ismount", lambda p: os.fspath(p) == str(mount) or ismount(p))
    code, _, err = run_cli(["run", capture, "-o", mount, "-q"], capsys)
    _one_line(code, err, str(mount), "mount point")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["usb"]


def test_a_name_longer_than_the_file_system_allows_is_refused_before_decoding(capture, tmp_path, monkeypatch,
                                                                               capsys):
    _no_decoding(monkeypatch)
    name = "n" * (os.pathconf(tmp_path, "PC_NAME_MAX") + 1)
    code, _, err = run_cli(["run", capture, "-o", tmp_path / name, "-q"], capsys)
    _one_line(code, err, f"{len(name)} bytes")
    code, _, err = run_cli(["relight", tmp_path / "x.ptm", "-o", tmp_path / (name + ".png"), "--light", "0,0,1"],
                           capsys)
    _one_line(code, err, "bytes")
    assert list(tmp_path.iterdir()) == []


def test_a_legal_250_byte_output_name_works(capture, tmp_path, capsys):
    out = tmp_path / ("é" * 125)  # 250 bytes in UTF-8
    for _ in range(2):  # made, then replaced
        code, _, err = run_cli(["run", capture, "-o", out, "-q", "--threads", "1"], capsys)
        assert code == 0, err
    assert (out / "mesh.ply").is_file()
    assert [p.name for p in tmp_path.iterdir()] == [out.name]  # no staging folder, no lock left


@_SETTINGS
@given(name=_NAMES)
@example(name="é" * 127 + "e")  # 255 bytes
def test_any_legal_name_can_be_an_output_folder_and_an_output_file(tmp_path_factory, name):
    parent = tmp_path_factory.mktemp("names")
    for _ in range(2):  # made, then replaced: the lock, staging and aside names all fit
        with staged_output(parent / name) as staged:
            (staged / "report.json").write_text("{}")
            staged.publish(["report.json"])
    assert [p.name for p in parent.iterdir()] == [name]
    with atomic_write(parent / name / "report.json", "w") as f:  # its temporary name fits too
        f.write("[]")
    assert sorted(p.name for p in (parent / name).iterdir()) == ["report.json"]


@_SETTINGS
@given(name=_NAMES, suffix=st.integers(0, 40))
def test_hidden_names_fit_and_differ(name, suffix):
    hidden = atomic.hidden_name(name, suffix)
    assert len(os.fsencode(hidden)) + suffix <= atomic.NAME_MAX and hidden.startswith(".")
    assert hidden == atomic.hidden_name(name, suffix)
    assert hidden != atomic.hidden_name(name + "x", suffix)
    if len(os.fsencode(name)) + 1 + suffix <= atomic.NAME_MAX:  # a name that fits is kept as it is
        assert hidden == "." + name


# ------------------------------------------------------------------------ a link to a folder


def test_a_link_to_a_folder_gets_the_result_where_it_points(capture, result, tmp_path, capsys):
    target = tmp_path / "disk" / "tablet"
    shutil.copytree(result, target)
    (target / "mesh.ply").write_bytes(b"the earlier result")
    link = tmp_path / "out"
    link.symlink_to(target)
    code, stdout, err = run_cli(["run", capture, "-o", link, "-q", "--threads", "1"], capsys)
    assert code == 0, err
    assert link.is_symlink() and link.resolve() == target  # the link stays
    assert (target / "mesh.ply").read_bytes() != b"the earlier result"
    assert str(target) in stdout  # the summary says where the result went
    assert sorted(p.name for p in tmp_path.iterdir()) == ["disk", "out"]
    assert [p.name for p in target.parent.iterdir()] == ["tablet"]


def test_a_link_to_a_file_gets_the_file_where_it_points(tmp_path):
    (tmp_path / "real.txt").write_text("old")
    (tmp_path / "link.txt").symlink_to(tmp_path / "real.txt")
    with atomic_write(tmp_path / "link.txt", "w") as f:
        f.write("new")
    assert (tmp_path / "link.txt").is_symlink() and (tmp_path / "real.txt").read_text() == "new"


# ------------------------------------------------------------------------ the user's files in a result


@pytest.mark.parametrize(("mine", "named"), [
    ("web/notes.txt", "web/notes.txt"),
    ("web/thumbs/a.png", "web/thumbs"),  # a folder in web/
    ("web/index.html/draft.html", "web/index.html"),  # a result's file name taken by a folder
    ("mesh.ply/notes.txt", "mesh.ply/notes.txt"),
    ("report.json/x", "report.json/x"),
])
def test_a_users_file_in_a_result_folder_is_never_replaced(result, tmp_path, capture, capsys, mine, named):
    out = tmp_path / "out"
    shutil.copytree(result, out)
    target = out / mine
    if target.parent.is_file():
        target.parent.unlink()
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text("years of work")
    before = _tree(out)
    with pytest.raises(InputError, match=f"not a reconstruct result: it holds {re.escape(named)}"), \
            staged_output(out):
        pass
    assert _tree(out) == before


def test_a_results_own_tree_is_replaced(result):
    """Every file a run writes, its web page's among them, is one a result may hold (README's
    table lists web/'s), so a second run into a result is never refused."""
    assert staging._foreign(result) == []
    assert {p.name for p in (result / "web").iterdir()} >= {"index.html", "viewer.json", "info.json"}
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    web_row = next(row for row in readme.split("## Output folder", 1)[1].splitlines() if row.startswith("| `web/`"))
    for name in (*WEB_FILES, "plane_0.jpg"):
        assert f"`{name}`" in web_row
        assert any(fnmatch.fnmatchcase(name, p) for p in staging._FOLDER_NAMES["web"]), name


@_SETTINGS
@given(name=st.text(st.characters(whitelist_categories=("Ll", "Lu", "Nd"), whitelist_characters="._-"),
                    min_size=1, max_size=20).filter(lambda n: n not in (".", "..")))
def test_only_the_web_pages_files_may_be_in_web(tmp_path_factory, name):
    out = tmp_path_factory.mktemp("web") / "out"
    (out / "web").mkdir(parents=True)
    (out / "web" / name).write_text("?")
    allowed = name in WEB_FILES or re.fullmatch(r"plane_.*\.jpg", name, re.S)
    assert staging._foreign(out) == ([] if allowed else [f"web/{name}"])


def test_an_output_folder_that_cannot_be_read_is_one_line(result, tmp_path, monkeypatch):
    out = tmp_path / "out"
    shutil.copytree(result, out)
    iterdir = Path.iterdir

    def unreadable(path):
        if path == out / "web":  # another user's folder, or a failing disk
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return iterdir(path)

    monkeypatch.setattr(Path, "iterdir", unreadable)
    with pytest.raises(InputError, match="cannot read the output folder \\(permission denied\\)") as info, \
            staged_output(out):
        pass
    assert info.value.path == str(out / "web")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_nul_in_an_output_name_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="NUL"), staged_output(tmp_path / "a\0b"):
        pass
    with pytest.raises(InputError, match="NUL"), atomic_write(tmp_path / "a\0b.png"):
        pass
    assert list(tmp_path.iterdir()) == []
