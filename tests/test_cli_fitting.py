"""``reconstruct lights``, the rank handling and the leave-one-out check of ``reconstruct run``."""

import json

import numpy as np
import pytest


from helpers import run_cli as _run
from data_synthetic.lights import dome_lights, ring_lights
from ptmcore.lp import write_lp


def test_lights_command_on_a_ring_and_a_dome(tmp_path, capsys):
    write_lp(tmp_path / "ring.lp", [f"{k}.jpg" for k in range(24)], ring_lights(24, 30.0))
    code, stdout, err = _run(["lights", tmp_path / "ring.lp", "-o", tmp_path / "ring.png"], capsys)
    assert code == 0, err
    assert "rank 5 of 6" in stdout and "elevation 30.0°" in stdout
    assert (tmp_path / "ring.png").stat().st_size > 1000
    write_lp(tmp_path / "dome.lp", [f"{k}.jpg" for k in range(48)], dome_lights(48))
    code, stdout, _ = _run(["lights", tmp_path / "dome.lp"], capsys)
    assert code == 0 and "rank 6 of 6" in stdout and "no problems found" in stdout


def test_lights_command_bad_file(tmp_path, capsys):
    (tmp_path / "bad.lp").write_text("2\na.jpg 0 0 1\n")
    code, _, err = _run(["lights", tmp_path / "bad.lp"], capsys)
    assert code == 2 and "bad.lp" in err


@pytest.mark.parametrize("solver", ["pinv", "lstsq", "rohde"])
def test_run_on_a_ring_reports_the_rank_and_stays_bounded(tmp_path, capsys, solver):
    from data_synthetic import write_capture

    info = write_capture(tmp_path / "cap", "sphere", shape=(48, 64), n_lights=16, seed=1,
                         lights=ring_lights(16, 40.0))
    out = tmp_path / "out"
    code, stdout, err = _run(["run", info.folder, "-o", out, "--solver", solver, "--normals", "ptm", "-q"], capsys)
    assert code == 0, err
    assert "rank 5 of 6" in stdout
    report = json.loads((out / "report.json").read_text())
    assert report["lights"]["rank"] == 5 and report["parameters"]["solver"] == solver
    from ptmcore.ptmfile import read_ptm

    # A rank-deficient layout must not blow the coefficients up (the .ptm holds 0–255 units).
    assert np.abs(read_ptm(out / "coefficients.ptm").coefficients).max() < 400  # measured 272


def test_leave_one_out_comparison_of_bases(tmp_path, capsys):
    from data_synthetic import write_capture

    info = write_capture(tmp_path / "cap", "tablet", shape=(60, 80), n_lights=24, seed=2, cast_shadows=False)
    out = tmp_path / "out"
    code, _, err = _run(["run", info.folder, "-o", out, "--loo", "-q"], capsys)
    assert code == 0, err
    loo = json.loads((out / "report.json").read_text())["leave_one_out"]
    assert set(loo["rms_levels"]) == {"ptm", "hsh2", "hsh3", "hsh4", "rbf", "bilinear"}
    # A Lambertian surface on a dome: hemispherical harmonics of order 3 or more predict
    # left-out photographs best, better than the biquadratic.
    levels = loo["rms_levels"]
    assert loo["best"] in ("hsh3", "hsh4") and levels["hsh3"] < levels["ptm"] and levels["hsh4"] < levels["ptm"]
    import tifffile

    assert tifffile.imread(out / "loo_ptm.tif").shape == (60, 80)
    assert tifffile.imread(out / "loo_bilinear.tif").shape == (60, 80)


def test_run_on_a_photometric_stereo_dataset_reports_accuracy(tmp_path, capsys):
    from test_psdataset import _write_dataset

    _write_dataset(tmp_path / "ds", n=12)
    out = tmp_path / "out"
    code, stdout, err = _run(["run", tmp_path / "ds", "-o", out, "-q"], capsys)
    assert code == 0, err
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"]["layout"] == "photometric-stereo dataset"
    # The intensities are divided out and Normal_gt.png is compared inside mask.png.
    assert report["accuracy"]["normals"]["mean_deg"] < 0.5
    assert (out / "normals.png").exists() and (out / "mesh.ply").exists()


def test_uneven_flash_fixed_by_estimated_or_given_intensities(tmp_path, capsys):
    from data_synthetic import write_capture
    from ptmcore.images import read_image

    import tifffile

    info = write_capture(tmp_path / "cap", "tablet", shape=(90, 120), n_lights=24, seed=3, noise=0.002)
    factors = np.random.default_rng(7).uniform(0.6, 1.0, 24)
    for path, f in zip(info.image_paths, factors):
        tifffile.imwrite(path, np.round(read_image(path) * f).astype(np.uint16))
    (tmp_path / "intensities.txt").write_text("\n".join(f"{f:.6f}" for f in factors) + "\n")
    errors = {}
    for name, extra in {"none": [], "estimate": ["--intensities", "estimate"],
                        "file": ["--intensities", tmp_path / "intensities.txt"]}.items():
        out = tmp_path / name
        code, _, err = _run(["run", info.folder, "-o", out, "-q", *extra], capsys)
        assert code == 0, err
        report = json.loads((out / "report.json").read_text())
        errors[name] = report["accuracy"]["normals"]["mean_deg"]
    assert errors["none"] > 2.0
    assert errors["estimate"] < 0.6 and errors["file"] < 0.6
    assert report["intensities"]["source"].endswith("intensities.txt")


def test_robust_fits_on_a_shiny_tablet(tmp_path, capsys):
    from data_synthetic import write_capture

    info = write_capture(tmp_path / "cap", "tablet", shape=(120, 160), n_lights=48, seed=4,
                         specular=0.6, shininess=40.0)
    errors = {}
    for normals, fit in [("ps", "plain"), ("ps", "irls"), ("ps", "trimmed"), ("ptm", "irls"),
                         ("ptm-debiased", "irls"), ("ptm-debiased", "plain")]:
        out = tmp_path / f"{normals}-{fit}"
        code, _, err = _run(["run", info.folder, "-o", out, "--normals", normals, "--fit", fit, "-q"], capsys)
        assert code == 0, err
        errors[normals, fit] = json.loads((out / "report.json").read_text())["accuracy"]["normals"]["mean_deg"]
    # Specular highlights pull plain least squares off; the robust fits leave them out (measured
    # mean: ps 5.88° plain, 0.46° irls, 0.50° trimmed; ptm-debiased 8.24° plain, 0.64° irls; ptm 3.72°).
    assert errors["ps", "irls"] < 1.0 < errors["ps", "plain"]
    assert errors["ps", "trimmed"] < 1.0
    assert errors["ptm-debiased", "irls"] < 1.5 < errors["ptm-debiased", "plain"]
    assert errors["ptm-debiased", "irls"] < errors["ptm", "irls"]
