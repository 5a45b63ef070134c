from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "ptmfitter_8x5"


@pytest.fixture
def shared_fixture() -> Path:
    if not SHARED.exists():
        pytest.skip(f"shared fixtures not found at {SHARED}")
    return SHARED


@pytest.fixture(autouse=True)
def _pillow_limit():
    """Every test starts with Pillow's own decompression-bomb limit: the command
    (cli.main.main, called in-process by many tests) raises it for the whole process
    (ptmcore.images.allow_large_images)."""
    from PIL import Image

    default = 1024 * 1024 * 1024 // 4 // 3  # Pillow's Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = default
    yield
    Image.MAX_IMAGE_PIXELS = default
