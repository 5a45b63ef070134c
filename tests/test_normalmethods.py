"""ptmcore.normalmethods: the normal methods and fits declared once, and everything that lists
or dispatches them reading that declaration."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from data_synthetic import write_capture
from ptmcore import (
    InputError,
    debiased_normals,
    fit_ptm,
    hemisphere_coefficients,
    lambertian_albedo,
    normals_from_ptm,
    photometric_stereo,
    robust_photometric_stereo,
    robust_ptm,
)
from ptmcore.normalmethods import FITS, NORMAL_METHODS
from reconstruct.pipeline import NearLights, RunOptions, estimate_normals, load_capture
from reconstruct.pipeline.options import choices
from reconstruct.report.summary import summary_rows


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("methods") / "capture"
    write_capture(folder, shape=(24, 32), n_lights=16, seed=5, specular=0.3)
    return load_capture(folder, RunOptions())


def _direct(stack, directions, normals: str, fit: str) -> np.ndarray:
    """The normals each (method, fit) stands for, called without the registry."""
    if normals == "ps":
        if fit == "plain":
            return photometric_stereo(stack, directions).normals
        return robust_photometric_stereo(stack, directions, method="irls" if fit == "lobe" else fit,
                                         lobe=fit == "lobe").normals
    if fit == "plain":
        coefficients = fit_ptm(stack, directions).coefficients
        if normals == "ptm":
            return normals_from_ptm(coefficients)
        return debiased_normals(coefficients, hemisphere_coefficients(directions))
    fitted = robust_ptm(stack, directions, method="irls" if fit == "lobe" else fit)
    return normals_from_ptm(fitted.ptm.coefficients) if normals == "ptm" else fitted.normals


@pytest.mark.parametrize("fit", list(FITS))
@pytest.mark.parametrize("normals", list(NORMAL_METHODS))
def test_every_method_and_fit_is_dispatched_to_its_function(capture, normals, fit):
    found = estimate_normals(capture, RunOptions(normals=normals, fit=fit, threads=1))
    expected = _direct(capture.stack, capture.lights.directions, normals, fit)
    np.testing.assert_allclose(found.normals, expected, atol=1e-6)
    if normals != "ps":  # the PTM's normals get the Lambertian albedo of their own
        np.testing.assert_allclose(found.albedo, lambertian_albedo(capture.stack, capture.lights.directions,
                                                                   found.normals), rtol=1e-5, atol=1e-7)


def test_the_command_line_lists_what_is_declared(capsys):
    from cli.main import main

    assert choices(RunOptions, "normals") == tuple(NORMAL_METHODS)
    assert choices(RunOptions, "fit") == tuple(FITS)
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for entry in [*NORMAL_METHODS.values(), *FITS.values()]:
        assert f"{entry.name}" in text and " ".join(entry.help.split()) in text


@pytest.mark.parametrize("normals", list(NORMAL_METHODS))
def test_the_report_says_which_method_made_the_normals(normals):
    report = {"parameters": {"normals": normals, "fit": "trimmed"}, "inputs": {"photographs": 16},
              "mesh": {"integrator": "masked"}}
    said = " ".join(value for _, value in summary_rows(report, None, None, object_name="tablet"))
    method = NORMAL_METHODS[normals]
    assert method.words.format(fit=FITS["trimmed"].words) in said


def test_a_method_for_distant_lights_only_refuses_near_ones(capture):
    near = NearLights(np.tile([16.0, 12.0, 200.0], (len(capture.stack), 1)), "test")
    with_near = dataclasses.replace(capture, near=near)
    distant_only = [m.name for m in NORMAL_METHODS.values() if m.near is None]
    assert distant_only == ["ptm-debiased"]
    with pytest.raises(InputError, match="ps or ptm"):
        estimate_normals(with_near, RunOptions(normals="ptm-debiased"))
