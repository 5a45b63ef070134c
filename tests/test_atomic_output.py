"""Issue 16: a result folder is the complete old result or the complete new one at every
instant, whatever is killed when; one run per folder at a time."""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from data_synthetic import write_capture

pytestmark = pytest.mark.skipif(os.name != "posix", reason="kills and locks: POSIX")


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("atomic") / "capture"
    write_capture(folder, shape=(48, 64), n_lights=12, seed=3)
    return folder


def _run(capture: Path, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "reconstruct", "run", str(capture), "-o", str(out), "-q",
                             "--pixel-size", "0.1", "--threads", "1", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _state(out: Path) -> tuple[frozenset[str], bool] | None:
    """The folder's file names and whether its report.json says --hsh; None when missing."""
    if not out.exists():
        return None
    names = frozenset(str(p.relative_to(out)) for p in out.rglob("*"))
    report = json.loads((out / "report.json").read_text())
    return names, bool(report["parameters"]["hsh"])


def test_a_killed_run_leaves_the_old_or_the_new_result(capture, tmp_path):
    out = tmp_path / "out"
    assert _run(capture, out).wait() == 0
    old = _state(out)
    saved = tmp_path.parent / f"{tmp_path.name}_old"  # outside tmp_path, whose listing is checked
    shutil.copytree(out, saved)
    probe = _run(capture, tmp_path / "probe", "--hsh")
    start = time.monotonic()
    assert probe.wait() == 0
    took = time.monotonic() - start
    new = _state(tmp_path / "probe")
    assert old != new and new[1] and not old[1]
    rng = random.Random(16)
    for _ in range(20):
        proc = _run(capture, out, "--hsh")
        time.sleep(rng.uniform(0.3, 1.05) * took)  # publishing is in the last tenth or so
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        state = _state(out)
        assert state in (old, new), state
        if state == new:  # start again from the old result (a copy: a run to remake it costs seconds)
            shutil.rmtree(out)
            shutil.copytree(saved, out)
    # What the killed runs left beside the folder goes with the next run on it.
    assert _run(capture, out).wait() == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "probe"]
    shutil.rmtree(saved)


@pytest.mark.parametrize("delay", [0.3, 1.0, 1.5, 2.0, 2.5])
def test_sigterm_stops_cleanly(capture, tmp_path, delay):
    out = tmp_path / "out"
    assert _run(capture, out).wait() == 0
    old = _state(out)
    proc = _run(capture, out, "--hsh")
    time.sleep(delay)  # from the imports to the report
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    if proc.returncode == 0:  # finished first on a fast machine
        pytest.skip("the run finished before SIGTERM")
    assert proc.returncode in (143, -signal.SIGTERM), err  # before the CLI's handler: the default
    assert "Traceback" not in err
    # The old result, or the new one when the signal came after the publication.
    assert _state(out) in (old, (old[0] | {"coefficients.rti"}, True))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging folder, no lock


@pytest.mark.parametrize(("delay", "again"), [(0.2, None), (0.3, None), (0.5, None), (0.8, None),
                                              (0.5, 0.0), (0.7, 0.02), (0.9, 0.05), (1.1, 0.01)])
def test_ctrl_c_once_or_twice_stops_cleanly(capture, tmp_path, delay, again):
    # Ctrl-C at any moment from the command's imports to the report (in the interpreter's own
    # start, its first hundredths of a second, Python prints a traceback), and a second one soon
    # after, while the first one's clean-up runs.
    out = tmp_path / "out"
    assert _run(capture, out).wait() == 0
    old = _state(out)
    proc = _run(capture, out, "--hsh")
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    if again is not None:
        time.sleep(again)
        proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    if proc.returncode == 0:
        pytest.skip("the run finished before Ctrl-C")
    # Before Python's own handler exists the signal's default action ends the process.
    assert proc.returncode in (130, -signal.SIGINT), err
    assert "Traceback" not in err
    assert err in ("", "reconstruct: interrupted\n"), err
    assert _state(out) in (old, (old[0] | {"coefficients.rti"}, True))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging folder, no lock


def test_two_runs_on_one_folder(capture, tmp_path):
    out = tmp_path / "out"
    first = _run(capture, out)
    deadline = time.monotonic() + 60
    lock = tmp_path / ".out.lock"
    while not lock.exists() and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    second = _run(capture, out, "--hsh")
    _, err = second.communicate()
    assert first.wait() == 0
    if not lock.exists() and second.returncode == 0:
        pytest.skip("the first run ended before the second started")
    assert second.returncode == 2, err
    assert len(err.strip().splitlines()) == 1 and "another reconstruct run" in err
    assert _state(out)[1] is False  # the first run's result


def test_a_signal_during_the_stop_lets_its_clean_up_finish(tmp_path, monkeypatch):
    """A second signal that lands while the first one's handler removes the staging folder (two
    Ctrl-C's at once; CI saw a ``.partial-….abandoned`` folder left behind) returns at once: the
    first handler's removal is not cut short by the second one ending the process."""
    from cli import signals
    from reconstruct.pipeline import staging

    folder = tmp_path / ".out.partial-0123abcd"
    (folder / "web").mkdir(parents=True)
    for i in range(20):
        (folder / "web" / f"plane_{i}.jpg").write_bytes(b"x" * 100)
    monkeypatch.setattr(staging, "_LIVE", {folder})
    monkeypatch.setattr(signals, "_stopping", False)
    monkeypatch.setattr(signals, "interrupted", lambda: signals.EXIT_INTERRUPTED)
    exits = []

    def fake_exit(status):
        exits.append(status)
        raise SystemExit(status)

    monkeypatch.setattr(os, "_exit", fake_exit)
    real_rmtree = staging.shutil.rmtree
    nested = []

    def rmtree_hit_by_a_signal(path, *args, **kwargs):
        if not nested:  # the second Ctrl-C arrives in the middle of the first one's removal
            nested.append(path)
            signals._terminate(signal.SIGINT, None)
        real_rmtree(path, *args, **kwargs)

    monkeypatch.setattr(staging.shutil, "rmtree", rmtree_hit_by_a_signal)
    with pytest.raises(SystemExit):
        signals._terminate(signal.SIGINT, None)
    assert nested and exits == [signals.EXIT_INTERRUPTED]
    assert list(tmp_path.iterdir()) == []
