"""Tests for reconstruct.surface.segment: the synthetic tablet against its ground-truth mask."""

from __future__ import annotations

import numpy as np
import pytest

from data_synthetic import SCENES, dome_lights, render
from reconstruct.surface.segment import foreground_mask

SHAPE = (192, 256)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


@pytest.fixture(scope="module")
def tablet():
    """The tablet scene and its albedo and normals estimated from a rendered capture.

    Plain per-channel least-squares photometric stereo over 24 dome lights, with sensor
    noise and cast shadows left in, so the cues are as imperfect as a real estimate's.
    """
    surface = SCENES["tablet"](SHAPE, seed=0)
    lights = dome_lights(24)
    images = np.clip(render(surface, lights, noise=0.005, seed=0), 0.0, 1.0)
    g = np.einsum("kn,nhwc->hwck", np.linalg.pinv(lights), images)  # (H, W, C, 3) = ρ_c n
    albedo = np.linalg.norm(g, axis=-1)
    g_sum = g.sum(axis=2)
    normals = g_sum / np.linalg.norm(g_sum, axis=-1, keepdims=True)
    return surface, albedo.astype(np.float32), normals.astype(np.float32)


# Measured on this scene: auto 0.9998, albedo 0.9999, normals 0.975 (the rim alone, filled).
@pytest.mark.parametrize(("method", "min_iou"), [("auto", 0.99), ("albedo", 0.99),
                                                  ("normals", 0.95)])
def test_tablet_matches_ground_truth(tablet, method: str, min_iou: float) -> None:
    surface, albedo, normals = tablet
    mask = foreground_mask(albedo, normals, method=method)
    assert mask.shape == SHAPE and mask.dtype == bool
    assert _iou(mask, surface.mask) >= min_iou


def test_albedo_only_and_grey_input(tablet) -> None:
    surface, albedo, _ = tablet
    assert _iou(foreground_mask(albedo), surface.mask) >= 0.99
    assert _iou(foreground_mask(albedo.mean(axis=-1)), surface.mask) >= 0.95


def test_object_touching_the_frame(tablet) -> None:
    """An object cut by the frame is kept up to the frame's edge, not eroded there."""
    surface, albedo, normals = tablet
    crop = np.s_[:, 60:]  # the tablet's left part runs off the frame
    mask = foreground_mask(albedo[crop], normals[crop])
    truth = surface.mask[crop]
    assert truth[:, 0].any()
    assert _iou(mask, truth) >= 0.99
    assert (mask[:, 0] ^ truth[:, 0]).sum() <= 4


def test_nan_pixels_are_tolerated(tablet) -> None:
    surface, albedo, normals = tablet
    albedo, normals = albedo.copy(), normals.copy()
    albedo[100:103, 100:103] = np.nan  # on the object: filled as a hole
    normals[5:8, 5:8] = np.nan  # on the background
    assert _iou(foreground_mask(albedo, normals), surface.mask) >= 0.99


def test_uniform_image_raises() -> None:
    rng = np.random.default_rng(0)
    albedo = np.full((*SHAPE, 3), 0.3, np.float32) + 0.003 * rng.standard_normal((*SHAPE, 3))
    normals = np.zeros((*SHAPE, 3), np.float32)
    normals[..., 2] = 1.0
    with pytest.raises(ValueError, match="no object stands out"):
        foreground_mask(albedo, normals)
    with pytest.raises(ValueError, match="no object stands out"):
        foreground_mask(np.zeros(SHAPE, np.float32))


def test_bad_arguments() -> None:
    albedo = np.zeros((*SHAPE, 3), np.float32)
    with pytest.raises(ValueError, match="method"):
        foreground_mask(albedo, method="magic")
    with pytest.raises(ValueError, match="needs the normals"):
        foreground_mask(albedo, method="normals")
    with pytest.raises(ValueError, match="normals must have shape"):
        foreground_mask(albedo, np.zeros((10, 10, 3)))
    with pytest.raises(ValueError, match="albedo_rgb"):
        foreground_mask(np.zeros((4, 5, 6, 7)))
