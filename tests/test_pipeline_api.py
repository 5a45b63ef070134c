"""The pipeline's public API: options that validate themselves, the CLI's choices derived from
them, staged output, re-entrant runs, and the stages composing to what ``run_capture`` gives."""

from __future__ import annotations

import dataclasses
import json
import os
import threading
from pathlib import Path

import numpy as np
import pytest

from data_synthetic import write_capture
from ptmcore.errors import InputError
from reconstruct.cli.parser import build_parser
from reconstruct.pipeline import (
    CompareOptions,
    RunOptions,
    choices,
    default,
    estimate_normals,
    integrate_surface,
    load_capture,
    resolve_mask,
    run_capture,
    staged_output,
)
from reconstruct.pipeline.staging import STAGING_PREFIX


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("cap") / "capture"
    write_capture(folder, shape=(48, 64), n_lights=16, seed=3)
    return folder


@pytest.mark.parametrize("field, value", [
    ("normals", "magic"), ("fit", "l1"), ("integrator", "poisson"), ("ptm_format", "rgba"),
    ("solver", "svd"), ("flatten", "poly9"), ("pixel_size", 0.0), ("pixel_size", float("nan")),
    ("step", 0), ("decimate", -3), ("solid", -1.0), ("distance", float("inf")),
    ("intrinsics", "1,2,3"), ("flatten_cutoff", 0.0), ("threads", 0),
])
def test_run_options_reject_bad_values_on_construction(field, value):
    with pytest.raises(InputError):
        RunOptions(**{field: value})


def test_run_options_reject_both_decimations_and_keep_keywords():
    with pytest.raises(InputError, match="not both"):
        RunOptions(decimate=100, max_error=0.1)
    opt = RunOptions(mask="auto", light_positions="none", lp="a/b.lp")
    assert opt.mask == "auto" and opt.light_positions == "none" and opt.lp == Path("a/b.lp")
    assert RunOptions(mask="m.png").mask == Path("m.png")
    with pytest.raises(InputError):
        dataclasses.replace(opt, normals="bogus")  # replace validates too


def test_compare_options_validate():
    with pytest.raises(InputError):
        CompareOptions(scan_units="furlong")
    with pytest.raises(InputError):
        CompareOptions(min_fraction=1.5)
    with pytest.raises(InputError):
        CompareOptions(tolerance=-1.0)


def test_cli_choices_and_defaults_come_from_the_options():
    parser = build_parser()
    run = parser._subparsers._group_actions[0].choices["run"]
    actions = {a.dest: a for a in run._actions}
    for name in ("normals", "fit", "integrator", "ptm_format", "solver", "flatten"):
        assert tuple(actions[name].choices) == choices(RunOptions, name)
        assert actions[name].default == default(RunOptions, name)
    assert tuple(actions["scan_units"].choices) == choices(CompareOptions, "scan_units")
    # Every option the CLI gives RunOptions is one of its fields, so none is lost on the way.
    args = parser.parse_args(["run", "cap", "-o", "out"])
    fields = {f.name for f in dataclasses.fields(RunOptions)}
    assert fields <= set(vars(args)), fields - set(vars(args))


def _result(staged, *names: str) -> None:
    """Write a minimal result (a report.json of this project and ``names``) and publish it."""
    (staged / "report.json").write_text(json.dumps({"versions": {"ptm-reconstruct": "test"}}))
    for name in names:
        (staged / name).parent.mkdir(parents=True, exist_ok=True)
        (staged / name).write_text(name)
    staged.publish(["report.json", *names])


def test_staged_output_locks_swaps_whole_folders_and_cleans(tmp_path):
    out = tmp_path / "out"
    with staged_output(out) as a:
        assert a.staging.parent == tmp_path and a.staging.name.startswith(".out" + STAGING_PREFIX)
        assert not out.exists()  # nothing appears before the result is complete
        # One run per folder: a second one refuses, naming the first one's process.
        with pytest.raises(InputError, match=rf"another reconstruct run \(process {os.getpid()}\)"), \
                staged_output(out):
            pass
        (a / "scratch.raw").write_text("not published")
        _result(a, "mesh.ply", "web/info.json")
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == ["mesh.ply", "report.json", "web", "web/info.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging folder, no lock left
    # A run that fails leaves the earlier result as it was.
    with pytest.raises(RuntimeError), staged_output(out) as c:
        (c / "height.tif").write_text("new")
        raise RuntimeError("a stage failed")
    assert (out / "mesh.ply").read_text() == "mesh.ply" and not (out / "height.tif").exists()
    # A new result replaces the whole folder: no file of the old one survives beside it.
    with staged_output(out) as d:
        _result(d, "height.tif")
    assert sorted(p.name for p in out.iterdir()) == ["height.tif", "report.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    # What is not a result of this project is never replaced, and a file is not a folder.
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("years of work")
    with pytest.raises(InputError, match="not a reconstruct result"), staged_output(tmp_path / "mine"):
        pass
    assert (tmp_path / "mine" / "thesis.tex").read_text() == "years of work"
    # Nor is a result beside which the user put a file of their own.
    (out / "notes.txt").write_text("the left edge is a modern repair")
    with pytest.raises(InputError, match="not a reconstruct result: it holds notes.txt"), staged_output(out):
        pass
    assert (out / "notes.txt").exists() and (out / "height.tif").exists()
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match="not a folder"), staged_output(tmp_path / "file"):
        pass
    with pytest.raises(InputError, match="empty path"), staged_output(""):
        pass


@pytest.mark.parametrize("exchange", [True, False])
def test_both_swaps_replace_the_result(tmp_path, monkeypatch, exchange):
    import reconstruct.pipeline.staging as staging

    if not exchange:  # a system without renameat2(RENAME_EXCHANGE): two renames
        monkeypatch.setattr(staging, "_exchange", lambda a, b: False)
    out = tmp_path / "out"
    for name in ("mesh.ply", "height.tif"):
        with staged_output(out) as s:
            _result(s, name)
    assert sorted(p.name for p in out.iterdir()) == ["height.tif", "report.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_figures_saved_from_the_preview_live_on_in_new_results(tmp_path):
    """The preview window saves into RESULT/preview/; a new run into the folder replaces the
    result, not the user's figures (hard links: the old result's files are gone)."""
    out = tmp_path / "out"
    with staged_output(out) as a:
        _result(a, "mesh.ply")
    (out / "preview").mkdir()
    (out / "preview" / "tablet_relit.png").write_bytes(b"figure")
    (out / "preview" / "profile_1.csv").write_text("distance,height")
    with staged_output(out) as b:
        _result(b, "height.tif")
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == [
        "height.tif", "preview", "preview/profile_1.csv", "preview/tablet_relit.png", "report.json"]
    assert (out / "preview" / "tablet_relit.png").read_bytes() == b"figure"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_staged_output_removes_what_dead_runs_left(tmp_path):
    out = tmp_path / "out"
    with staged_output(out) as a:
        _result(a, "mesh.ply")
    # A run killed while building, and one killed between the two renames of the fallback swap.
    (tmp_path / f".out{STAGING_PREFIX}dead").mkdir()
    (tmp_path / f".out{STAGING_PREFIX}dead" / "mesh.ply").write_text("half")
    aside = tmp_path / ".out.old-dead"
    aside.mkdir()
    os.rename(out, aside / "result")
    (tmp_path / ".out.lock").write_text("999999")  # a lock file whose process died
    with staged_output(out) as b:
        assert (out / "mesh.ply").read_text() == "mesh.ply"  # put back before anything else
        _result(b, "height.tif")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert sorted(p.name for p in out.iterdir()) == ["height.tif", "report.json"]
    # Parent folders a failed run created go again.
    with pytest.raises(RuntimeError), staged_output(tmp_path / "a" / "b" / "out"):
        raise RuntimeError("failed")
    assert not (tmp_path / "a").exists()


def test_two_runs_in_two_threads_of_one_process(capture, tmp_path):
    results, errors = {}, []

    def work(name: str) -> None:
        try:
            results[name] = run_capture(capture, tmp_path / name, RunOptions(pixel_size=0.05))
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(n,)) for n in ("a", "b")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    a, b = (np.load(tmp_path / n / "normals.npy") for n in ("a", "b"))
    np.testing.assert_array_equal(a, b)
    for n in ("a", "b"):
        names = {p.name for p in (tmp_path / n).iterdir()}
        assert {"mesh.ply", "mesh.obj", "coefficients.ptm", "report.json", "report.html"} <= names
        assert not any(name.startswith(STAGING_PREFIX) for name in names)
        report = json.loads((tmp_path / n / "report.json").read_text())
        assert report["stages"]["normals"]["peak_rss_mb"] > 0


def test_stages_reproduce_run_capture(capture, tmp_path):
    opt = RunOptions(pixel_size=0.05, mask="auto")
    result = run_capture(capture, tmp_path / "out", opt)
    loaded = load_capture(capture, opt)
    found = estimate_normals(loaded, opt)
    np.testing.assert_array_equal(found.normals, np.load(tmp_path / "out" / "normals.npy"))
    albedo_rgb = loaded.stack.chroma * found.albedo[..., None]
    mask = resolve_mask(opt.mask, loaded.mask, albedo_rgb, found.normals)
    surface = integrate_surface(found.normals, mask, opt)
    import tifffile

    np.testing.assert_array_equal(surface.height, tifffile.imread(tmp_path / "out" / "height.tif"))
    assert result.report.mesh.integrator == surface.integrator
    assert result.report.to_dict()["inputs"]["layout"] == loaded.layout


def test_report_json_keys(capture, tmp_path):
    run_capture(capture, tmp_path / "out", RunOptions(pixel_size=0.05))
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert list(report) == ["inputs", "parameters", "height_unit", "capture_checks", "albedo_scale", "lights", "light_model",
                            "intensities", "reflectance_lobe", "ptm", "relighting", "leave_one_out", "accuracy", "mesh",
                            "seconds",
                            "stages", "peak_rss_mb", "peak_rss_scope", "versions", "warnings"]
    # The whole run's peak: the largest stage's, so no stage can hide it.
    assert report["peak_rss_mb"] == max(s["peak_rss_mb"] for s in report["stages"].values()) > 0
    # The files are written ("write") while later stages compute; the run's wall time is at
    # least any stage's.
    stages = report["stages"]
    assert list(stages) == ["decode", "ptm", "basis", "normals", "albedo", "integrate", "mesh", "report", "write"]
    assert report["seconds"] >= max(s["seconds"] for s in stages.values())
    assert report["accuracy"]["ground_truth"].endswith("ground_truth")
    assert set(report["mesh"]) == {"vertices", "faces", "unit", "step", "integrator", "integrator_reason",
                                   "decimation"}
    assert report["parameters"]["step"] == report["mesh"]["step"]
    assert report["light_model"] == {"type": "distant", "detail": "one light direction per photograph"}


def test_the_names_a_result_may_hold_cover_the_documented_layout():
    """A folder is replaced only when it holds nothing but result files (staging._OUTPUT_NAMES):
    every file README's "Output folder" table documents, and every file a comparison writes,
    must be among them, or a rerun into such a result would be refused."""
    import fnmatch
    import re

    from reconstruct.pipeline.compare_run import COMPARISON_FILES
    from reconstruct.pipeline.staging import _OUTPUT_NAMES

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    table = readme.split("## Output folder", 1)[1].split("\n## ", 1)[0]
    documented = {n.rstrip("/") for row in table.splitlines() if row.startswith("| `")
                  for n in re.findall(r"`([^`]+)`", row.split("|")[1])}
    assert {"coefficients.ptm", "web", "mesh.obj", "report.json"} <= documented
    for name in documented | set(COMPARISON_FILES):
        assert any(fnmatch.fnmatchcase(name, pattern) for pattern in _OUTPUT_NAMES), name
    # The page's table of files (report.summary._FILES) describes the same names: a file a
    # result may hold gets its own description on the page, not "written by the run".
    from reconstruct.report.summary import _FILES

    described = {name.split("/")[0] for name, _, _ in _FILES}
    for pattern in _OUTPUT_NAMES:
        if pattern != "preview":  # the preview window's folder: not a file the page lists
            assert any(fnmatch.fnmatchcase(name, pattern) for name in described), pattern
    for name in described:
        assert any(fnmatch.fnmatchcase(name, pattern) for pattern in _OUTPUT_NAMES), name


def test_the_published_basis_is_chosen_on_the_capture_and_reported(capture, tmp_path):
    run_capture(capture, tmp_path / "out", RunOptions(pixel_size=0.05))
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    chosen = report["relighting"]
    assert chosen["chosen_by"] == "leave-one-out" and chosen["unit"] == "8-bit sRGB levels"
    assert (chosen["name"], chosen["encoding"]) == (chosen["scores"][0]["name"], chosen["scores"][0]["encoding"])
    info = json.loads((tmp_path / "out" / "web" / "info.json").read_text())
    viewer = json.loads((tmp_path / "out" / "web" / "viewer.json").read_text())
    assert viewer["basis"] == chosen["name"] and viewer["encoding"] == chosen["encoding"]
    assert info["type"] in ("ptm", "hsh", "rbf", "bilinear")


def test_outputs_relight_writes_only_the_relightable_files(capture, tmp_path):
    result = run_capture(capture, tmp_path / "out", RunOptions(outputs="relight", basis="rbf", basis_encoding="srgb"))
    names = set(result.files)
    assert {"coefficients.ptm", "web/info.json", "web/index.html", "report.json", "report.html"} <= names
    assert not any(n.startswith(("normals", "height", "mesh", "albedo")) for n in names)
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["relighting"]["name"] == "rbf" and report["relighting"]["chosen_by"] == "asked"
    assert report["mesh"] is None and "normals" not in report["stages"]
