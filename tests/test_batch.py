"""reconstruct batch: sources and manifests, failures isolated, resume, the lock, Dask clusters."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from data_synthetic import write_capture
from ptmcore.errors import InputError
from reconstruct.batch import batch_lock, read_manifest, run_batch
from reconstruct.batch.sources import discover
from reconstruct.pipeline import RunOptions
from helpers import run_cli

distributed = pytest.importorskip("distributed")
import dask  # noqa: E402  (with distributed)

from reconstruct.batch.scheduler import LOCAL_CONFIG  # noqa: E402

OPT = RunOptions(pixel_size=0.05)


@pytest.fixture(scope="module")
def collection(tmp_path_factory) -> Path:
    """Two good captures, one with a corrupt photograph, one folder that is no capture."""
    root = tmp_path_factory.mktemp("collection")
    for k, name in enumerate(("tablet_a", "tablet_b", "broken")):
        write_capture(root / name, shape=(40, 56), n_lights=12, seed=k)
    (root / "broken" / "img_003.tif").write_bytes(b"not a TIFF")
    (root / "notes").mkdir()
    (root / "notes" / "readme.txt").write_text("field notes")
    return root


@pytest.fixture(scope="module")
def client():
    """An in-process local cluster (threads), quick to start."""
    # The batch's own settings (its profiler off: reconstruct.batch.scheduler.LOCAL_CONFIG).
    with dask.config.set(LOCAL_CONFIG), distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0", silence_logs=40) as cluster:
        with distributed.Client(cluster) as c:
            yield c


def _copy(collection: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "collection"
    shutil.copytree(collection, dst)
    return dst


def test_discover_takes_sub_folders_and_says_what_it_skipped(collection):
    items, skipped = discover([collection], OPT)
    assert sorted(i.name for i in items) == ["broken", "tablet_a", "tablet_b"]
    assert [p.name for p, _ in skipped] == ["notes"]
    items, _ = discover([collection / "tablet_a", collection / "tablet_a" / "lights.lp"], OPT)
    assert [i.name for i in items] == ["tablet_a", "tablet_a-2"]
    with pytest.raises(InputError, match="no such"):
        discover([collection / "missing"], OPT)


def test_a_bad_capture_fails_alone_and_the_rest_completes(collection, client, tmp_path):
    out = tmp_path / "out"
    seen = []
    rows = run_batch([collection], out, OPT, client=client, progress=lambda row, done, total: seen.append(done))
    status = {r.name: r.status for r in rows}
    assert status == {"broken": "failed", "tablet_a": "done", "tablet_b": "done"}
    broken = next(r for r in rows if r.name == "broken")
    assert "img_003.tif" in broken.error
    assert sorted(seen) == [1, 2, 3]
    for name in ("tablet_a", "tablet_b"):
        assert (out / name / "mesh.ply").is_file() and (out / name / "report.html").is_file()
        assert json.loads((out / name / "report.json").read_text())["fingerprint"]
    table = list(csv.DictReader((out / "batch.csv").open()))
    assert [r["name"] for r in table] == [r.name for r in rows]
    done = next(r for r in table if r["name"] == "tablet_a")
    assert done["photographs"] == "12" and done["width"] == "56" and done["height_unit"] == "mm"
    assert float(done["accuracy_mean_deg"]) < 5 and float(done["height_max"]) > float(done["height_min"])
    assert len(json.loads((out / "batch.json").read_text())) == 3
    page = (out / "index.html").read_text()
    assert page.index("broken") < page.index("tablet_a")  # failures first


def test_resume_skips_complete_objects_and_redoes_changed_or_killed_ones(collection, client, tmp_path):
    captures = _copy(collection, tmp_path)
    out = tmp_path / "out"
    run_batch([captures / "tablet_a", captures / "tablet_b"], out, OPT, client=client)
    # A killed object: its staging folder left behind, its report.json not yet published.
    (out / "tablet_b" / "report.json").unlink()
    (out / "tablet_b" / ".partial-dead").mkdir()
    (out / "tablet_b" / ".partial-dead" / "mesh.ply").write_text("half")
    (out / ".tablet_b.partial-dead").mkdir()  # the staging folder of this version, beside it
    (out / ".tablet_b.partial-dead" / "mesh.ply").write_text("half")
    # An earlier version's batch killed between its two renames: the old result is put back.
    os.rename(out / "tablet_a", out / ".replaced-tablet_a")
    (out / ".running-tablet_a").mkdir()
    (out / ".running-tablet_a" / "mesh.ply").write_text("half")
    t0 = time.perf_counter()
    rows = run_batch([captures / "tablet_a", captures / "tablet_b"], out, OPT, client=client)
    assert {r.name: r.status for r in rows} == {"tablet_a": "skipped", "tablet_b": "done"}
    assert not list((out / "tablet_b").glob(".partial-*"))
    assert not list(out.glob(".running-*")) and not list(out.glob(".replaced-*"))
    assert not list(out.glob(".tablet_*"))
    assert time.perf_counter() - t0 < 30
    # A photograph changed: only that object runs again; --force redoes all.
    photo = captures / "tablet_a" / "img_000.tif"
    os.utime(photo, ns=(photo.stat().st_atime_ns, photo.stat().st_mtime_ns + 10**9))
    rows = run_batch([captures / "tablet_a", captures / "tablet_b"], out, OPT, client=client)
    assert {r.name: r.status for r in rows} == {"tablet_a": "done", "tablet_b": "skipped"}
    rows = run_batch([captures / "tablet_a", captures / "tablet_b"], out, OPT, client=client, force=True)
    assert {r.status for r in rows} == {"done"}
    # A photograph spoilt since: the object fails and its earlier result stays whole.
    before = (out / "tablet_b" / "mesh.ply").read_bytes()
    (captures / "tablet_b" / "img_005.tif").write_bytes(b"spoilt")
    rows = run_batch([captures / "tablet_b"], out, OPT, client=client)
    assert rows[0].status == "failed" and "img_005.tif" in rows[0].error
    assert (out / "tablet_b" / "mesh.ply").read_bytes() == before
    assert (out / "tablet_b" / "report.json").is_file() and not list(out.glob(".running-*"))


def test_a_finished_batch_run_again_starts_no_cluster(collection, client, tmp_path, monkeypatch):
    import reconstruct.batch.scheduler as scheduler

    captures = _copy(collection, tmp_path)
    out = tmp_path / "out"
    run_batch([captures / "tablet_a", captures / "tablet_b"], out, OPT, client=client)

    def no_cluster(*args, **kwargs):
        raise AssertionError("a cluster was started for a batch with nothing to do")

    monkeypatch.setattr(scheduler, "_client", no_cluster)
    seen = []
    rows = run_batch([captures / "tablet_a", captures / "tablet_b"], out, OPT,
                     progress=lambda row, done, total: seen.append((row.name, done, total)))
    assert [r.status for r in rows] == ["skipped", "skipped"]
    assert seen == [("tablet_a", 1, 2), ("tablet_b", 2, 2)]
    assert (out / "batch.csv").is_file() and (out / "index.html").is_file()


def test_manifest_overrides_and_names(collection, client, tmp_path):
    manifest = tmp_path / "objects.csv"
    rel = os.path.relpath(collection, tmp_path)
    manifest.write_text("capture,name,pixel_size,normals,integrator\n"
                        f"{rel}/tablet_a,K.1234,0.1,ptm,\n"
                        f"{rel}/tablet_b,,,,dct\n")
    items = read_manifest(manifest, OPT)
    assert [i.name for i in items] == ["K.1234", "tablet_b"]
    assert items[0].options.pixel_size == 0.1 and items[0].options.normals == "ptm"
    assert items[1].options.pixel_size == 0.05 and items[1].options.integrator == "dct"
    rows = run_batch(None, tmp_path / "out", OPT, manifest=manifest, client=client)
    assert [r.status for r in rows] == ["done", "done"] and rows[0].normals == "ptm"
    report = json.loads((tmp_path / "out" / "K.1234" / "report.json").read_text())
    assert report["parameters"]["pixel_size"] == 0.1


@pytest.mark.parametrize("body, message", [
    ("capture,pixelsize\ntablet_a,0.1\n", "unknown column"),
    ("name\nx\n", "no capture column"),
    ("capture,pixel_size\ntablet_a,0.1\nmissing,0.1\n", "line 3: capture not found"),
    ("capture,pixel_size\ntablet_a,-1\n", "line 2: --pixel-size"),
    ("capture,normals\ntablet_a,magic\n", "line 2: --normals"),
    ("capture,glb\ntablet_a,perhaps\n", "line 2: glb"),
    ("capture,scan\ntablet_a,scan.ply\n", "line 2: scan not found"),
])
def test_manifest_errors_name_the_row_and_nothing_runs(collection, tmp_path, body, message, capsys):
    manifest = collection / f"bad_{abs(hash(body))}.csv"
    manifest.write_text(body)
    try:
        with pytest.raises(InputError, match=message):
            read_manifest(manifest, OPT)
        code, _, err = run_cli(["batch", "--manifest", manifest, "-o", tmp_path / "out"], capsys)
        assert code == 2 and ("line" in err or "column" in err)
        assert not (tmp_path / "out").exists()
    finally:
        manifest.unlink()


def test_a_second_batch_on_the_same_folder_refuses(collection, client, tmp_path):
    out = tmp_path / "out"
    with batch_lock(out):
        with pytest.raises(InputError, match="another batch"):
            run_batch([collection / "tablet_a"], out, OPT, client=client)
    # Released: the next one runs.
    assert run_batch([collection / "tablet_a"], out, OPT, client=client)[0].status == "done"


def _kill_once(marker: str) -> None:
    """Make this worker process die the first time any worker starts an object."""
    import reconstruct.batch.runner as runner

    original = runner._reconstruct

    def dying(*args, **kwargs):
        try:
            fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return original(*args, **kwargs)
        os.close(fd)
        os._exit(1)

    runner._reconstruct = dying


def test_an_object_whose_worker_dies_is_retried(collection, tmp_path):
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=":0", silence_logs=50) as cluster:
        with distributed.Client(cluster) as c:
            c.run(_kill_once, str(tmp_path / "killed"))
            rows = run_batch([collection / "tablet_a"], tmp_path / "out", OPT, client=c)
    assert (tmp_path / "killed").exists()
    assert rows[0].status == "done", rows[0].error


def test_cli_batch_on_a_separate_scheduler_and_worker(collection, tmp_path, capsys):
    bin_dir = Path(sys.executable).parent
    info = tmp_path / "scheduler.json"
    procs = [subprocess.Popen([str(bin_dir / "dask"), "scheduler", "--port", "0", "--dashboard-address", ":0",
                               "--scheduler-file", str(info)], stderr=subprocess.DEVNULL)]
    try:
        for _ in range(300):
            if info.exists() and info.read_text().strip():
                break
            time.sleep(0.1)
        address = json.loads(info.read_text())["address"]
        procs.append(subprocess.Popen([str(bin_dir / "dask"), "worker", address, "--nworkers", "1", "--nthreads", "1",
                                       "--no-dashboard"], stderr=subprocess.DEVNULL))
        with distributed.Client(address) as c:
            c.wait_for_workers(1, timeout=60)
        code, out, err = run_cli(["batch", collection / "tablet_a", collection / "broken", "-o", tmp_path / "out",
                                  "--scheduler", address, "--pixel-size", "0.05"], capsys)
        assert code == 1, err
        assert "1 done" in out and "1 failed" in out and "broken" in out
        assert (tmp_path / "out" / "tablet_a" / "mesh.obj").is_file()
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(timeout=30)


def test_cli_refuses_bad_batch_arguments(collection, tmp_path, capsys, monkeypatch):
    code, _, err = run_cli(["batch", tmp_path / "nothing", "-o", tmp_path / "out"], capsys)
    assert code == 2 and "no such" in err
    code, _, err = run_cli(["batch", "-o", tmp_path / "out"], capsys)
    assert code == 2 and "--manifest" in err
    # A refused port is retried until the connection's timeout: a second here, not the 20 s a
    # scheduler slow to answer is given.
    monkeypatch.setattr("reconstruct.batch.scheduler.CONNECT_SECONDS", 1)
    code, _, err = run_cli(["batch", collection / "tablet_a", "-o", tmp_path / "out",
                            "--scheduler", "tcp://127.0.0.1:9"], capsys)
    assert code == 2 and "cannot reach the Dask scheduler" in err


def test_local_cluster_size_follows_memory_and_cores(collection):
    from reconstruct.batch import choose_workers, estimate_peak_mb

    items, _ = discover([collection], OPT)
    peak = max(estimate_peak_mb(i) for i in items)
    assert 400 < peak < 500  # 12 photographs of 56×40: the interpreter and libraries dominate
    assert choose_workers(items, cores=16, available_mb=100 * peak) == len(items)  # never more than objects
    assert choose_workers(items, cores=2, available_mb=100 * peak) == 2  # never more than cores
    assert choose_workers(items, cores=16, available_mb=2.5 * peak) == 2  # what memory allows
    assert choose_workers(items, cores=16, available_mb=0.5 * peak) == 1  # at least one


# Stopping a batch: Ctrl-C in a terminal reaches every process of the foreground group.

@pytest.fixture(scope="module")
def slow_collection(tmp_path_factory) -> Path:
    """Captures that take a second or two each, so that objects are caught running."""
    root = tmp_path_factory.mktemp("slow")
    for k in range(4):
        write_capture(root / f"tablet_{k}", shape=(360, 480), n_lights=32, seed=k)
    return root


def _staged(out: Path) -> list[str]:
    """The hidden staging folders and locks of objects running (or left) in ``out``."""
    return sorted(p.name for p in out.glob(".*") if p.name != ".batch.lock")


def _wait_for(condition, timeout: float = 120.0) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_a_stopped_object_removes_what_it_staged_and_keeps_its_earlier_result(slow_collection, tmp_path):
    from reconstruct.batch.runner import BatchStopped, run_object, stop_objects

    (item,), _ = discover([slow_collection / "tablet_0"], OPT)
    out = tmp_path / "out"
    assert run_object(item, out).status == "done"
    before = sorted((p.name, p.stat().st_mtime_ns) for p in (out / item.name).iterdir())
    rows = []
    worker = threading.Thread(target=lambda: rows.append(run_object(item, out, force=True, token="t1")))
    worker.start()
    assert _wait_for(lambda: any(".partial-" in n for n in _staged(out)))
    stop_objects("t1")
    worker.join(60)
    assert not worker.is_alive()
    assert rows[0].status == "failed" and "stopped" in rows[0].error, rows[0]
    assert _staged(out) == []  # its staging folder and its lock are gone
    assert sorted((p.name, p.stat().st_mtime_ns) for p in (out / item.name).iterdir()) == before
    # Another batch's objects on the same worker go on; a stopped batch starts no more.
    assert run_object(item, out, force=True, token="t2").status == "done"
    assert "before this object started" in run_object(item, out, force=True, token="t1").error
    assert issubclass(BatchStopped, BaseException) and not issubclass(BatchStopped, Exception)


def _log_error(text: str) -> None:
    import logging

    logging.getLogger("distributed.worker").error(text)


def test_a_closing_local_cluster_keeps_its_workers_quiet(capfd):
    # What a worker's heartbeat logs when the scheduler closes under it (a race of Dask's own
    # shutdown) reached the terminal after the batch's last line; once the batch quiets them,
    # its worker processes print nothing below CRITICAL.
    from reconstruct.batch.scheduler import _quiet_workers

    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=":0", silence_logs=40) as cluster:
        with distributed.Client(cluster) as c:
            c.run(_log_error, "heard before")
            _quiet_workers(c)
            c.run(_log_error, "heard after")
    err = capfd.readouterr().err
    assert "heard before" in err, err  # the capture sees a worker's stderr
    assert "heard after" not in err, err


def test_a_batch_quiets_its_local_cluster_before_closing_it(collection, tmp_path, monkeypatch):
    from reconstruct.batch import scheduler

    seen = []
    monkeypatch.setattr(scheduler, "_quiet_workers",
                        lambda c: seen.append((c.status, len(c.scheduler_info()["workers"]))))
    rows = run_batch([collection / "tablet_a"], tmp_path / "out", OPT, workers=1)
    assert rows[0].status == "done", rows[0].error
    assert seen == [("running", 1)]  # once, while the client and its worker were still up


@pytest.mark.parametrize("signals", [["SIGINT"], ["SIGINT", "SIGINT"], ["SIGTERM"]])
def test_ctrl_c_stops_a_batch_with_one_line(slow_collection, tmp_path, signals):
    # Sent to the whole process group, as a terminal does: the workers must not print
    # tracebacks of their own, and the objects running must not leave staging folders.
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "reconstruct", "batch", str(slow_collection), "-o", str(out),
                             "--workers", "2", "--threads", "1", "-q"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        if not _wait_for(lambda: any(".partial-" in n for n in _staged(out)) or proc.poll() is not None):
            pytest.fail("no object started within 120 s")
        for k, name in enumerate(signals):
            if k:
                time.sleep(0.1)
            os.killpg(proc.pid, getattr(signal, name))
        _, err = proc.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    if proc.returncode == 0:
        pytest.skip("the batch finished before the signal")
    if signals == ["SIGTERM"]:
        # At once: the workers die with the batch's process, and what they staged goes with
        # the next run on those objects (the README's promise for killed runs).
        assert proc.returncode == 143, err
        assert err == "reconstruct: stopped (SIGTERM); output folders keep their earlier results\n", err
    else:
        assert proc.returncode == 130, err
        assert err == "reconstruct: interrupted\n", err  # no worker's traceback, no tracker's warning
    if signals == ["SIGINT"]:
        assert _staged(out) == []  # the objects running were stopped and removed what they staged
    # Every process of the batch has ended (the workers too).
    assert _wait_for(lambda: not _group_alive(proc.pid), timeout=10)


def _group_alive(pgid: int) -> bool:
    """Whether a process of group ``pgid`` still runs; zombies count as ended (their parent,
    the batch, has ended and init reaps them)."""
    for entry in Path("/proc").iterdir():
        try:
            stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):  # not a process, or one that has just gone
            continue
        if int(stat[2]) == pgid and stat[0] != "Z":
            return True
    return False
