import signal
from pathlib import Path

import pytest

# A test run started with Ctrl-C ignored (`make test &` from a script, nohup: the shell sets
# SIGINT to SIG_IGN, which every child inherits) would leave the command's Ctrl-C handling
# untested, and the tests that interrupt a run would wait for runs that cannot be interrupted.
# Python's own handler here gives the commands the tests start the default disposition, as a
# user's terminal does.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

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
