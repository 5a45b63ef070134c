"""reconstruct warm-up: the kernels compiled by small synthetic runs, nothing left behind."""

import tempfile
from pathlib import Path

from reconstruct.cli.main import main
from reconstruct.pipeline.warmup import WARM_UP_RUNS, warm_up


def _leftovers() -> list[Path]:
    return sorted(Path(tempfile.gettempdir()).glob("reconstruct-warm-up-*"))


def test_warm_up_runs_each_capture_and_removes_its_folder():
    before = _leftovers()
    seen = []
    result = warm_up([("jpeg8", {}), ("tiff16", {"normals": "ptm", "integrator": "dct"})],
                     progress=lambda done, total: seen.append((done, total)))
    assert (result.runs, result.failed) == (2, []) and result.seconds > 0
    assert seen == [(1, 2), (2, 2)]
    assert _leftovers() == before


def test_a_failed_run_is_reported_and_the_others_still_run():
    result = warm_up([("tiff16", {"normals": "no-such-method"}), ("tiff16", {})])
    assert result.runs == 2 and len(result.failed) == 1 and "no-such-method" in result.failed[0]


def test_the_default_runs_reach_every_normal_method_fit_and_both_encodings():
    from reconstruct.pipeline.options import RunOptions, choices

    options = [extra for _, extra in WARM_UP_RUNS]
    assert {enc for enc, _ in WARM_UP_RUNS} == {"tiff16", "jpeg8"}
    for name in ("normals", "fit"):
        reached = {o.get(name, getattr(RunOptions(), name)) for o in options}
        assert reached == set(choices(RunOptions, name)), name


def test_cli_warm_up(capsys):
    assert main(["warm-up"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("Compiling the numerical kernels") and f"{len(WARM_UP_RUNS)}/{len(WARM_UP_RUNS)}" in out
    assert "the next runs start without compiling" in out
