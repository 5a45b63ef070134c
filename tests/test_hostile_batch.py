"""Hostile input to ``reconstruct batch`` (issue 36): manifests that are malformed, huge or not
files, names that collide with the batch's own files or are too long, a scheduler address that
is none, absurd worker counts, inputs changed behind a resume, failures without a message, and
``batch.csv`` cells a spreadsheet would take for formulas."""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from data_synthetic import write_capture
from ptmcore.atomic import atomic_write
from ptmcore.errors import InputError
from reconstruct.batch import read_manifest, run_batch
from reconstruct.batch import runner, scheduler, sources
from reconstruct.batch.rows import FAILED, BatchItem, BatchRow, write_rows
from reconstruct.pipeline import RunOptions
from helpers import run_cli

distributed = pytest.importorskip("distributed")
import dask  # noqa: E402  (with distributed)

from reconstruct.batch.scheduler import LOCAL_CONFIG  # noqa: E402

OPT = RunOptions(pixel_size=0.05)
FAST = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    """A small capture, ``cap/``, beside which manifests are written."""
    root = tmp_path_factory.mktemp("hostile_batch")
    write_capture(root / "cap", shape=(24, 32), n_lights=8, seed=0)
    return root / "cap"


@pytest.fixture(scope="module")
def client():
    """An in-process local cluster (threads), quick to start."""
    # The batch's own settings (its profiler off: reconstruct.batch.scheduler.LOCAL_CONFIG).
    with dask.config.set(LOCAL_CONFIG), distributed.LocalCluster(
            n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0", silence_logs=40) as cluster:
        with distributed.Client(cluster) as c:
            yield c


def _manifest(capture: Path, body: str, name: str = "objects.csv") -> Path:
    path = capture.parent / name
    path.write_text(body, encoding="utf-8", newline="")
    return path


# 1. batch.csv: no cell a spreadsheet would take for a formula.

_RISKY = ("=", "+", "-", "@", "\t", "\r")


@FAST
@given(texts=st.lists(st.text(alphabet=st.sampled_from("=+-@\t\r\n\"',;a1 ."), max_size=6), min_size=3, max_size=3),
       low=st.floats(-1e6, 1e6, allow_nan=False), high=st.floats(-1e6, 1e6, allow_nan=False))
def test_batch_csv_cells_never_start_a_formula_and_numbers_stay_numbers(tmp_path, texts, low, high):
    name, source, error = texts
    row = BatchRow(name, source, FAILED, error, seconds=1.5, height_min=low, height_max=high, warnings=2)
    write_rows(tmp_path, [row])
    with open(tmp_path / "batch.csv", newline="", encoding="utf-8") as f:
        (read,) = list(csv.DictReader(f))
    for field, original in (("name", name), ("source", source), ("error", error)):
        cell = read[field]
        assert not cell.startswith(_RISKY)
        assert cell == ("'" + original if original.startswith(_RISKY) else original)
    # Negative numbers stay numbers a spreadsheet can sum.
    assert float(read["height_min"]) == low and float(read["height_max"]) == high
    assert read["status"] == FAILED and read["warnings"] == "2"


# 2, 3, 4, 12. Manifests: quotes left open, extra cells, thousands of bad rows, special files.

def test_an_unterminated_quote_names_its_line_and_drops_no_row(capture, tmp_path, capsys):
    manifest = _manifest(capture, 'capture,name\ncap,a\ncap,"b\ncap,c\ncap,d\n', "quote.csv")
    with pytest.raises(InputError, match=r"quote\.csv: line 3: a quote opened on this line is never closed"):
        read_manifest(manifest, OPT)
    code, _, err = run_cli(["batch", "--manifest", manifest, "-o", tmp_path / "out"], capsys)
    assert code == 2 and err.count("\n") == 1 and "line 3" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()
    # Closed on a later line, it would swallow the rows between into one cell.
    manifest = _manifest(capture, 'capture,name\ncap,a\ncap,"b\ncap,c"\ncap,d\n', "quote.csv")
    with pytest.raises(InputError, match=r"line 3: a quote opened on this line closes only on line 4"):
        read_manifest(manifest, OPT)


@FAST
@given(names=st.lists(st.text(alphabet=st.sampled_from('ab-,"\n\r \x00\u00e9'), max_size=8), min_size=1, max_size=5),
       encoding=st.sampled_from(["utf-8", "utf-8-sig", "utf-16", "utf-32"]))
def test_a_manifest_read_keeps_one_object_per_line_or_refuses_it(capture, names, encoding):
    """Whatever the name cells hold (quotes, commas, line breaks, NUL), in any encoding with
    a byte-order mark, an accepted manifest gives one object per line that has a cell, and a
    refused one says so in one line that names the manifest."""
    body = "capture,name\n" + "".join(f"cap,{n}\n" for n in names)
    manifest = capture.parent / "random.csv"
    manifest.write_bytes(body.encode(encoding))
    try:
        items = read_manifest(manifest, OPT)
    except InputError as exc:
        message = str(exc)
        assert message.startswith(str(manifest)) and "\n" not in message and "\r" not in message
        return
    lines = list(io.StringIO(body, newline=""))[1:]
    with_cells = [k + 2 for k, line in enumerate(lines) if any(c.strip() for c in next(csv.reader([line]), []))]
    assert [i.row for i in items] == with_cells


def test_a_row_with_more_cells_than_the_header_names_its_line(capture):
    manifest = _manifest(capture, "capture,name\ncap,a,extra\ncap,b\n", "extra.csv")
    with pytest.raises(InputError, match=r"line 2: 3 cells, more than the header's 2 columns") as info:
        read_manifest(manifest, OPT)
    assert "None" not in str(info.value)
    # Empty cells past the header, as spreadsheets export them, are no problem.
    manifest = _manifest(capture, "capture,name\ncap,a,,\n", "extra.csv")
    assert [i.name for i in read_manifest(manifest, OPT)] == ["a"]


def test_a_column_given_twice_is_refused(capture):
    manifest = _manifest(capture, "capture,name,pixel_size,name\ncap,a,0.1,b\n", "twice.csv")
    with pytest.raises(InputError, match=r"twice\.csv: column\(s\) given twice in the header: 'name'$"):
        read_manifest(manifest, OPT)


def test_thousands_of_bad_rows_give_a_short_message(capture):
    body = "capture,glb\n" + "".join(f"cap,{'maybe' * 20}{k}\n" for k in range(10_000))
    manifest = _manifest(capture, body, "many.csv")
    with pytest.raises(InputError) as info:
        read_manifest(manifest, OPT)
    message = str(info.value)
    assert len(message) < 1200 and message.endswith("and 9997 more")
    assert "line 2: glb" in message and "line 5: glb" not in message


def test_a_huge_manifest_is_refused_unread(capture):
    manifest = capture.parent / "huge.csv"
    with open(manifest, "wb") as f:
        f.write(b"capture\ncap\n")
        f.truncate(sources.MAX_MANIFEST_BYTES + 1)  # sparse: nothing is written
    try:
        with pytest.raises(InputError, match=r"huge\.csv: the manifest is [\d,]+ bytes, more than"):
            read_manifest(manifest, OPT)
    finally:
        manifest.unlink()


def test_a_fifo_as_manifest_is_refused_without_waiting(tmp_path):
    fifo = tmp_path / "objects.csv"
    os.mkfifo(fifo)
    outcome = []

    def read() -> None:
        try:
            read_manifest(fifo, OPT)
        except InputError as exc:
            outcome.append(str(exc))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(10)
    if reader.is_alive():  # blocked opening it: a writer lets it go
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        reader.join(10)
        pytest.fail("reading a FIFO as the manifest blocked")
    assert outcome and "named pipe" in outcome[0]


def test_dev_zero_as_manifest_is_refused_in_one_line(tmp_path):
    # In a process of its own with bounded memory: a reader without a bound would eat it all.
    code = ("import resource; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30));"
            "from reconstruct.cli.main import main; raise SystemExit(main(['batch', '--manifest', '/dev/zero', '-o', "
            f"{str(tmp_path / 'out')!r}]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          cwd=Path(__file__).parents[1])
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "/dev/zero: is a device, not a manifest" in done.stderr


# 5. A failure says something useful, on one line, even without a message of its own.

@pytest.mark.parametrize("exc, words", [
    (MemoryError(), "ran out of memory during the normals stage: run fewer objects at once"),
    (KeyError(), "KeyError during the normals stage: mapping key not found"),
    (AssertionError(), "AssertionError during the normals stage: assertion failed"),
    (ValueError("a library's\nmessage\r\n" * 1000), "ValueError during the normals stage: a library's message a"),
])
def test_a_failure_s_message_says_something_on_one_line(capture, tmp_path, monkeypatch, exc, words):
    def failing(item, folder, print_, progress):
        if progress is not None:
            progress("normals", 0, 1)
        raise exc

    monkeypatch.setattr(runner, "_reconstruct", failing)
    row = runner.run_object(BatchItem("a", capture, OPT), tmp_path)
    assert row.status == FAILED and words in row.error
    assert "\n" not in row.error and "\r" not in row.error and len(row.error) < 600


# 6. A resume redoes an object when any input it reads changed, even at the same size and time.

def _rewrite_keeping_size_and_time(path: Path, data: bytes) -> None:
    before = path.stat()
    assert len(data) == before.st_size
    path.write_bytes(data)
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))


def _flip_last_byte(path: Path) -> None:
    data = path.read_bytes()
    _rewrite_keeping_size_and_time(path, data[:-1] + bytes([data[-1] ^ 1]))


@pytest.mark.parametrize("changed", ["mask", "outside_lp", "ground_truth", "scan", "light_positions", "intensities"])
def test_the_fingerprint_follows_every_input_s_content(capture, tmp_path, changed):
    cap = tmp_path / "cap"
    shutil.copytree(capture, cap)
    extra = tmp_path / "elsewhere"
    extra.mkdir()
    (extra / "mask.png").write_bytes(b"0123456789")
    shutil.copy(next(cap.glob("*.lp")), extra / "lights.lp")
    (extra / "light_positions.csv").write_text("img_000.tif,1,2,3\n")
    (extra / "intensities.txt").write_text("1.0\n" * 8)
    scan = cap / "scan.ply"
    options = {"mask": extra / "mask.png", "ground_truth": cap / "ground_truth",
               "intensities": str(extra / "intensities.txt")}
    if changed in ("outside_lp", "light_positions"):
        # The .lp elsewhere lists the capture's photographs.
        lines = (extra / "lights.lp").read_text().splitlines()
        (extra / "lights.lp").write_text("\n".join([lines[0], *(f"{cap}/{ln}" for ln in lines[1:])]) + "\n")
        options["lp"] = extra / "lights.lp"
    item = BatchItem("a", cap, dataclasses.replace(OPT, **options), scan=scan)
    before = runner.fingerprint(item)
    assert runner.fingerprint(dataclasses.replace(item, options=dataclasses.replace(item.options, threads=3))) == before
    target = {"mask": extra / "mask.png", "outside_lp": extra / "lights.lp", "intensities": extra / "intensities.txt",
              "ground_truth": cap / "ground_truth" / "normals.npy", "scan": scan,
              "light_positions": extra / "light_positions.csv"}[changed]
    _flip_last_byte(target)
    assert runner.fingerprint(item) != before


def test_the_fingerprint_follows_photographs_an_outside_lp_lists(capture, tmp_path):
    cap, photos = tmp_path / "cap", tmp_path / "photos"
    shutil.copytree(capture, cap)
    photos.mkdir()
    for p in cap.glob("img_*.tif"):
        os.rename(p, photos / p.name)
    lp = next(cap.glob("*.lp"))
    lines = lp.read_text().splitlines()
    lp.write_text("\n".join([lines[0], *(f"../photos/{ln}" for ln in lines[1:])]) + "\n")
    item = BatchItem("a", cap, OPT)
    before = runner.fingerprint(item)
    photo = photos / "img_003.tif"
    os.utime(photo, ns=(photo.stat().st_atime_ns, photo.stat().st_mtime_ns + 10**9))
    assert runner.fingerprint(item) != before


# 7, 8. Names: the batch's own files', and names too long for the file system.

def test_names_of_the_batch_s_own_files_get_a_suffix():
    assert sources.unique_names(["batch.csv", "index.html", "thumbnails", "Batch.JSON", "index.html"]) == \
        ["batch.csv-2", "index.html-2", "thumbnails-2", "Batch.JSON-2", "index.html-3"]


def test_an_object_named_index_html_runs_beside_the_gallery(capture, client, tmp_path):
    manifest = _manifest(capture, "capture,name\ncap,index.html\ncap,-minus\n", "own.csv")
    out = tmp_path / "out"
    rows = run_batch(None, out, OPT, manifest=manifest, client=client)
    assert [(r.name, r.status) for r in rows] == [("index.html-2", "done"), ("-minus", "done")], rows
    assert (out / "index.html").is_file() and (out / "index.html-2" / "report.json").is_file()
    # 11. The lock goes with the batch.
    assert not (out / scheduler.LOCK_NAME).exists()
    names = [r["name"] for r in csv.DictReader(io.StringIO((out / "batch.csv").read_text()))]
    assert names == ["index.html-2", "'-minus"]


def test_a_name_too_long_for_the_file_system_is_refused_before_anything_runs(capture, client, tmp_path):
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    longest = limit - scheduler.NAME_MARGIN
    manifest = _manifest(capture, f"capture,name\ncap,{'n' * longest}\ncap,{'x' * (longest + 1)}\n", "long.csv")
    out = tmp_path / "out"
    with pytest.raises(InputError, match=rf"object name\(s\) too long: x{{40}}…; .* at most {longest} bytes"):
        run_batch(None, out, OPT, manifest=manifest, client=client)
    assert not out.exists()
    # The longest name taken runs through, and its thumbnails' names fit.
    manifest = _manifest(capture, f"capture,name\ncap,{'n' * longest}\n", "long.csv")
    (row,) = run_batch(None, out, OPT, manifest=manifest, client=client)
    assert row.status == "done", row.error
    assert (out / "thumbnails" / f"{row.name}_relit.jpg").is_file()
    with atomic_write(out / "thumbnails" / f"{row.name}_height.png") as f:
        f.write(b"fits")


def test_the_name_margin_is_the_longest_thumbnail_suffix():
    from reconstruct.batch.gallery import THUMBNAILS

    assert scheduler.NAME_MARGIN == max(len(os.fsencode(s)) for s in THUMBNAILS.values())


# 9, 11. A scheduler address that is none, or cannot be reached: one line, nothing left.

@pytest.mark.parametrize("address", ["not a url", "tcp://host", "foo://host:8786", "host:99999", "host:x"])
def test_a_scheduler_address_that_is_none_is_one_line(capture, tmp_path, capsys, address):
    code, _, err = run_cli(["batch", capture, "-o", tmp_path / "out", "--scheduler", address], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert "is not a Dask scheduler's address" in err and "tcp://HOST:PORT" in err
    assert not (tmp_path / "out").exists()


def test_an_unreachable_scheduler_leaves_no_lock_and_no_folder(capture, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(scheduler, "CONNECT_SECONDS", 1, raising=False)
    existing = tmp_path / "existing"
    existing.mkdir()
    for out in (tmp_path / "new", existing):
        code, _, err = run_cli(["batch", capture, "-o", out, "--scheduler", "tcp://127.0.0.1:9"], capsys)
        assert code == 2 and err.count("\n") == 1 and "cannot reach the Dask scheduler" in err
    assert not (tmp_path / "new").exists()
    assert list(existing.iterdir()) == []


def test_a_killed_batch_s_lock_is_taken_over_and_removed(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / scheduler.LOCK_NAME).write_text("")  # left by a batch killed (its flock went with it)
    with scheduler.batch_lock(out):
        with pytest.raises(InputError, match="another batch"):
            with scheduler.batch_lock(out):
                pass
        assert (out / scheduler.LOCK_NAME).exists()
    assert list(out.iterdir()) == []


def test_a_lock_file_removed_under_a_waiting_batch_is_locked_afresh(tmp_path, monkeypatch):
    """The batch ending removes its lock file: one that opened it just before must not hold
    a lock on a file that no longer exists while a third batch locks the new one."""
    out = tmp_path / "out"
    out.mkdir()
    path = out / scheduler.LOCK_NAME
    real_flock = scheduler.fcntl.flock
    calls = []

    def flock_after_removal(fd, how):
        if not calls:  # the first batch ends between this one's open and its flock
            path.unlink()
        calls.append(fd)
        return real_flock(fd, how)

    monkeypatch.setattr(scheduler.fcntl, "flock", flock_after_removal)
    with scheduler.batch_lock(out):
        assert len(calls) == 2 and path.exists()
        monkeypatch.setattr(scheduler.fcntl, "flock", real_flock)
        with pytest.raises(InputError, match="another batch"):
            with scheduler.batch_lock(out):
                pass


# 10. --workers beyond the machine.

def test_workers_are_bounded_by_cpus_and_memory_with_a_warning(capture):
    items = [BatchItem(f"o{k}", capture, OPT) for k in range(8)]
    peak = runner.estimate_peak_mb(items[0])
    said = []
    assert runner.choose_workers(items, 2, 100 * peak, 1000, said.append) == 2
    assert len(said) == 1 and "1000 workers are more than this machine allows: 2 CPU(s)" in said[0]
    assert runner.choose_workers(items, 16, 3.5 * peak, 1000, said.append) == 3
    assert runner.choose_workers(items, 16, 100 * peak, 4, said.append) == 4 and len(said) == 2
    assert runner.choose_workers(items[:2], 16, 100 * peak, 4, said.append) == 2 and len(said) == 2


def test_a_batch_asked_for_1000_workers_starts_no_more_than_the_cpus(capture, tmp_path, monkeypatch):
    started = {}

    class Refused(Exception):
        pass

    def local_cluster(**kw):
        started.update(kw)
        raise Refused

    monkeypatch.setattr(distributed, "LocalCluster", local_cluster)
    items = [BatchItem(f"o{k}", capture, OPT) for k in range(64)]
    monkeypatch.setattr(scheduler, "collect_items", lambda *a: items)
    lines = []
    with pytest.raises(Refused):
        run_batch([capture], tmp_path / "out", OPT, workers=1000, echo=lines.append)
    assert 1 <= started["n_workers"] <= os.cpu_count()
    assert any(line.startswith("warning: 1000 workers are more than") for line in lines)
    assert not (tmp_path / "out").exists()


# Reading back an object's folder: a report that is no JSON object, or not a file, is no result.

def _within(seconds: float, call) -> list:
    """``[call()]``, or a test failure if it blocks for ``seconds``."""
    outcome = []
    thread = threading.Thread(target=lambda: outcome.append(call()), daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), "blocked"
    return outcome


@pytest.mark.parametrize("kind", ["list", "fifo"])
def test_an_object_folder_with_a_hostile_report_is_redone(capture, tmp_path, kind):
    from reconstruct.batch.gallery import write_thumbnails

    folder = tmp_path / "a"
    folder.mkdir()
    for name in ("report.html", "mesh.ply"):
        (folder / name).write_text("x")
    if kind == "list":
        (folder / "report.json").write_text("[]")
    else:
        os.mkfifo(folder / "report.json")
    item = BatchItem("a", capture, OPT)
    try:
        assert _within(10, lambda: runner.is_complete(folder, item, runner.fingerprint(item))) == [False]
        assert _within(10, lambda: write_thumbnails(folder, tmp_path / "thumbnails", "a")) == [{}]
    finally:
        if kind == "fifo":  # let a reader blocked on it go
            with contextlib.suppress(OSError):
                os.close(os.open(folder / "report.json", os.O_WRONLY | os.O_NONBLOCK))


def test_a_server_that_is_no_dask_scheduler_is_one_line(capture, tmp_path, capsys):
    """Whatever answers at the address (here a length of exabytes, as an HTTP server's reply
    read as Dask's frames would give), the batch says so in one line."""
    import socket

    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def answer() -> None:
        with contextlib.suppress(OSError):
            conn, _ = server.accept()
            conn.sendall(b"\x01\x00\x00\x00\x00\x00\x00\x00" + b"\xff" * 64)
            conn.recv(1)

    threading.Thread(target=answer, daemon=True).start()
    try:
        code, _, err = run_cli(["batch", capture, "-o", tmp_path / "out", "--scheduler", f"tcp://127.0.0.1:{port}"],
                               capsys)
    finally:
        server.close()
    assert code == 2 and err.count("\n") == 1, err
    assert "answered, but not as a Dask scheduler does" in err
    assert not (tmp_path / "out").exists()


def test_sources_and_manifest_paths_the_system_refuses_are_one_line(capture, tmp_path, capsys):
    too_long = tmp_path / ("a" * (os.pathconf(tmp_path, "PC_NAME_MAX") + 1))
    fifo = tmp_path / "capture.ptm"
    os.mkfifo(fifo)
    for source, words in ((too_long, "cannot read it (File name too long)"),
                          (fifo, "not a capture: give a folder, an .lp file or a .ptm file")):
        code, _, err = run_cli(["batch", source, "-o", tmp_path / "out"], capsys)
        assert code == 2 and err.count("\n") == 1 and words in err, err
    manifest = _manifest(capture, f"capture\n{too_long.name}\ncap\n", "toolong.csv")
    with pytest.raises(InputError, match=r"line 2: File name too long: .{59}…$"):
        read_manifest(manifest, OPT)
