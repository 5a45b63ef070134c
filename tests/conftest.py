from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "ptmfitter_8x5"


@pytest.fixture
def shared_fixture() -> Path:
    if not SHARED.exists():
        pytest.skip(f"shared fixtures not found at {SHARED}")
    return SHARED
