"""``reconstruct compare`` and ``reconstruct run --scan``."""

import json

import numpy as np
import pytest

from reconstruct.cli.main import main

from helpers import run_cli as _run


@pytest.fixture(scope="module")
def reconstructed(tmp_path_factory):
    from data_synthetic import write_capture

    root = tmp_path_factory.mktemp("cmp")
    info = write_capture(root / "cap", "tablet", shape=(90, 120), n_lights=24, seed=8)
    out = root / "out"
    assert main(["run", str(info.folder), "-o", str(out), "--pixel-size", str(info.pixel_size), "-q",
                 "--scan", str(info.scan_path)]) == 0
    return info, out


def test_run_with_scan_writes_the_comparison(reconstructed):
    info, out = reconstructed
    for name in ("comparison.json", "distances.ply", "histogram.png"):
        assert (out / name).exists(), name
    report = json.loads((out / "comparison.json").read_text())
    stats = report["statistics_mm"]
    assert stats["overlap_fraction"] > 0.9 and stats["rms"] < 0.1
    # The scan was moved by a known rigid transform: the alignment undoes it.
    truth = np.loadtxt(info.ground_truth_dir / "scan_transform.txt")
    found = np.asarray(report["alignment"]["transform_scan_to_reconstruction"])
    composed = found @ truth
    angle = np.degrees(np.arccos(np.clip((np.trace(composed[:3, :3]) - 1) / 2, -1, 1)))
    assert angle < 0.5


def test_compare_tolerance_sets_the_exit_status(reconstructed, tmp_path, capsys):
    info, out = reconstructed
    code, stdout, err = _run(["compare", out, info.scan_path, "-o", tmp_path / "a", "--tolerance", "1"], capsys)
    assert code == 0 and "PASS" in stdout, err
    code, stdout, _ = _run(["compare", out, info.scan_path, "-o", tmp_path / "b", "--tolerance", "0.001"], capsys)
    assert code == 1 and "FAIL" in stdout
    report = json.loads((tmp_path / "b" / "comparison.json").read_text())
    assert report["tolerance"]["passed"] is False


def test_compare_bad_inputs(reconstructed, tmp_path, capsys):
    info, out = reconstructed
    code, _, err = _run(["compare", out, info.scan_path, "-o", tmp_path / "c", "--scan-units", "m"], capsys)
    assert code == 2 and "--scan-units" in err
    code, _, err = _run(["compare", out, tmp_path / "missing.ply", "-o", tmp_path / "d"], capsys)
    assert code == 2 and "missing.ply" in err
    code, _, err = _run(["run", info.folder, "-o", tmp_path / "e", "--scan", info.scan_path], capsys)
    assert code == 2 and "--pixel-size" in err


def test_compare_reports_progress_stage_by_stage(reconstructed, tmp_path):
    """``compare`` (and ``run --scan``) take 15 s at 24 MP: every stage reports its progress,
    in order, from 0 to its total, under names that do not clash with the run's own."""
    from reconstruct.pipeline import run_compare
    from reconstruct.pipeline.compare_run import ScanStep

    info, out = reconstructed
    calls = []
    run_compare(out, info.scan_path, tmp_path / "cmp", progress=lambda *call: calls.append(call))
    stages = list(dict.fromkeys(stage for stage, _, _ in calls))
    assert stages == ["scan_read", "scan_align", "scan_distances", "scan_write", "scan_report"]
    for stage in stages:
        seen = [(done, total) for s, done, total in calls if s == stage]
        assert seen[0][0] == 0 and seen[-1][0] == seen[-1][1] > 0, (stage, seen)
    # The alignment, the longest, advances step by step: features, global registration, ICP.
    assert [done for s, done, _ in calls if s == "scan_align"] == [0, 1, 2, 3]
    calls.clear()
    ScanStep(info.scan_path, progress=lambda *call: calls.append(call))
    assert calls == [("scan_read", 0, 1), ("scan_read", 1, 1)]
