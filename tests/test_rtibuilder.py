"""Captures as archives keep them: RTIBuilder projects (photographs in jpeg-exports/, the light
file in assembly-files/ naming them by Windows paths), --lp from elsewhere, and a batch that
says what it skipped."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from data_synthetic import write_capture
from helpers import run_cli
from ptmcore.errors import InputError
from ptmcore.lp import read_lp
from reconstruct.batch.sources import discover
from reconstruct.pipeline import RunOptions
from reconstruct.pipeline.projects import locate_photographs, project_lp


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("rtib") / "capture"
    write_capture(folder, shape=(40, 48), n_lights=12, seed=8, encoding="jpeg8")
    return folder


def _project(capture: Path, root: Path, name: str = "tablet") -> Path:
    """``capture`` laid out as RTIBuilder leaves a project, its .lp naming the photographs by
    the absolute Windows paths of the machine that built it."""
    project = root / name
    (project / "jpeg-exports").mkdir(parents=True)
    (project / "assembly-files").mkdir()
    (project / "finished-files").mkdir()
    lights = read_lp(capture / "lights.lp")
    lines = [str(len(lights))]
    for path, d in zip(lights.paths, lights.directions):
        shutil.copy(path, project / "jpeg-exports" / path.name)
        lines.append(f"C:\\Users\\imaging\\Desktop\\{name}\\jpeg-exports\\{path.name} {d[0]:.6f} {d[1]:.6f} {d[2]:.6f}")
    (project / "assembly-files" / f"{name}.lp").write_text("\n".join(lines) + "\n")
    return project


def test_run_takes_a_project_folder(capture, tmp_path, capsys):
    project = _project(capture, tmp_path)
    out = tmp_path / "out"
    code, _, err = run_cli(["run", project, "-o", out, "-q", "--outputs", "relight"], capsys)
    assert code == 0, err
    report = json.loads((out / "report.json").read_text())
    assert Path(report["inputs"]["lp"]).parent.name == "assembly-files"
    lights = locate_photographs(read_lp(project_lp(project)), project)
    assert {p.parent.name for p in lights.paths} == {"jpeg-exports"}
    code, out_text, err = run_cli(["check", project], capsys)
    assert code == 0, err


def test_lp_from_elsewhere_takes_the_photographs_of_the_capture_folder(capture, tmp_path, capsys):
    # The light file alone in another folder, naming the photographs by bare names: they are
    # looked for in the capture folder first.
    elsewhere = tmp_path / "lights"
    elsewhere.mkdir()
    shutil.copy(capture / "lights.lp", elsewhere / "dome.lp")
    lights = locate_photographs(read_lp(elsewhere / "dome.lp"), capture)
    assert {p.parent for p in lights.paths} == {capture}
    code, _, err = run_cli(["run", capture, "--lp", elsewhere / "dome.lp", "-o", tmp_path / "o", "-q",
                            "--outputs", "relight"], capsys)
    assert code == 0, err


def test_a_photograph_found_nowhere_is_named_with_where_it_was_looked_for(capture, tmp_path):
    project = _project(capture, tmp_path)
    next((project / "jpeg-exports").iterdir()).unlink()
    with pytest.raises(InputError, match=r"not found; looked in .*assembly-files.*jpeg-exports"):
        locate_photographs(read_lp(project_lp(project)), project)


def test_several_light_files_in_assembly_files_are_named(capture, tmp_path, capsys):
    project = _project(capture, tmp_path)
    shutil.copy(project / "assembly-files" / "tablet.lp", project / "assembly-files" / "tablet_old.lp")
    code, _, err = run_cli(["run", project, "-o", tmp_path / "o", "-q"], capsys)
    assert code == 2 and "several .lp files" in err and "tablet_old.lp" in err and "--lp" in err


def test_a_batch_finds_projects_and_says_what_it_skipped(capture, tmp_path):
    drawer = tmp_path / "drawer"
    for name in ("BM_1", "BM_2"):
        _project(capture, drawer, name)
    (drawer / "notes").mkdir()
    items, skipped = discover([drawer], RunOptions())
    assert [i.name for i in items] == ["BM_1", "BM_2"]
    assert [(p.name, "RTIBuilder" in why) for p, why in skipped] == [("notes", True)]
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("x")
    with pytest.raises(InputError, match=r"no capture found .*skipped notes: not a capture.*readme.txt: not a .ptm"):
        discover([tmp_path / "empty"], RunOptions())
    (tmp_path / "bare").mkdir()
    with pytest.raises(InputError, match="it is empty"):
        discover([tmp_path / "bare"], RunOptions())
