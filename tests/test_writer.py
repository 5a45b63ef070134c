"""Files written in background threads (reconstruct.pipeline.writer) and a run that uses them."""

from __future__ import annotations

import threading
import time

import pytest

from data_synthetic.capture import write_capture
from ptmcore.errors import InputError
from reconstruct.pipeline import RunOptions, run_capture
from reconstruct.pipeline.writer import FileWriter


def test_jobs_run_beside_the_caller_and_wait_returns_their_names(tmp_path):
    started = threading.Event()
    release = threading.Event()

    def slow(path):
        started.set()
        release.wait(5)
        path.write_text("slow")

    with FileWriter(2) as writer:
        writer.submit(["a.txt"], slow, tmp_path / "a.txt")
        writer.submit(["b.txt", "c.txt"], lambda: [(tmp_path / n).write_text(n) for n in ("b.txt", "c.txt")])
        assert started.wait(5)  # the caller goes on while "a" is being written
        writer.wait_for("b.txt")
        assert (tmp_path / "b.txt").read_text() == "b.txt" and not (tmp_path / "a.txt").exists()
        assert writer.names == ["a.txt", "b.txt", "c.txt"]
        writer.wait_for("not-a-job.txt")  # nothing writes it: at once
        release.set()
        assert writer.wait() == ["a.txt", "b.txt", "c.txt"]
    assert (tmp_path / "a.txt").read_text() == "slow"


def test_a_failed_job_raises_in_the_caller():
    def fail():
        raise InputError("disk full")

    with pytest.raises(InputError, match="disk full"):
        with FileWriter(1) as writer:
            writer.submit(["x"], fail)
    writer = FileWriter(1)
    writer.submit(["x"], fail)
    with pytest.raises(InputError, match="disk full"):
        writer.wait_for("x")
    writer.close()


def test_leaving_on_an_error_drops_waiting_jobs_and_waits_for_running_ones(tmp_path):
    done = []
    started = threading.Event()

    def job(k):
        started.set()
        time.sleep(0.2)
        done.append(k)

    with pytest.raises(RuntimeError, match="the run failed"):
        with FileWriter(1) as writer:
            for k in range(5):
                writer.submit([f"{k}"], job, k)
            assert started.wait(5)
            raise RuntimeError("the run failed")
    # The running job finished before the block was left (nothing writes into a removed
    # staging folder afterwards); the waiting ones never started.
    assert done == [0]
    time.sleep(0.3)
    assert done == [0]


def test_a_failed_background_write_fails_the_run_and_publishes_nothing(tmp_path, monkeypatch):
    capture = tmp_path / "capture"
    write_capture(capture, shape=(32, 40), n_lights=12, seed=1)

    def broken(*args, **kwargs):
        raise InputError("cannot write mesh.ply: no space left on device")

    monkeypatch.setattr("reconstruct.pipeline.stages.write_ply", broken)
    samplers = {t for t in threading.enumerate() if t.name == "rss-sampler"}
    with pytest.raises(InputError, match="no space left"):
        run_capture(capture, tmp_path / "out", RunOptions(pixel_size=0.1))
    assert not (tmp_path / "out").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["capture"]  # no staging folder left either
    # The stage "write", left open by the error, was ended: its memory sampler stopped.
    assert {t for t in threading.enumerate() if t.name == "rss-sampler"} <= samplers


def test_check_raises_a_failed_job_without_waiting(tmp_path):
    release = threading.Event()

    def fail():
        raise InputError("disk full")

    writer = FileWriter(2)
    try:
        writer.submit(["slow"], release.wait, 5)
        writer.submit(["x"], fail)
        deadline = time.monotonic() + 5
        with pytest.raises(InputError, match="disk full"):
            while time.monotonic() < deadline:  # "slow" still running: check never waits for it
                writer.check()
                time.sleep(0.01)
        assert not release.is_set()
    finally:
        release.set()
        writer.close()


def test_meshes_without_the_maps_take_the_texture_array(tmp_path):
    import numpy as np

    from reconstruct.mesh.grid import grid_mesh
    from reconstruct.pipeline.stages import write_meshes

    texture = np.full((6, 7, 3), 200, np.uint8)
    mesh = grid_mesh(np.zeros((6, 7), np.float32), texture=texture)
    with FileWriter(1) as writer:
        names = write_meshes(tmp_path, writer, mesh, texture, RunOptions())
        writer.wait()
    assert {"mesh.obj", "mesh_texture.png", "mesh.ply"} <= set(names)
    assert (tmp_path / "mesh_texture.png").read_bytes().startswith(b"\x89PNG")
