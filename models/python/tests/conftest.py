"""Fixtures shared by every test folder: the official reduced reference (skipped where the team's
data is absent). Plain helpers and paths are in `tests.common`."""

from pathlib import Path

import numpy as np
import pytest

from tests.common import OFFICIAL_SMALL_DIR


@pytest.fixture(scope="session")
def official_small_dir() -> Path:
    if not OFFICIAL_SMALL_DIR.is_dir():
        pytest.skip(f"reference outputs not found at {OFFICIAL_SMALL_DIR} (set C4G_SHARED)")
    return OFFICIAL_SMALL_DIR


@pytest.fixture(scope="session")
def official_reference(official_small_dir):
    return np.load(official_small_dir / "reference.npz")


@pytest.fixture(scope="session")
def official_small_model(official_small_dir):
    from c4g.model.checkpoint import load_checkpoint
    from c4g.model.config import OFFICIAL_SMALL

    return load_checkpoint(official_small_dir / "c4g_official_small.ckpt", OFFICIAL_SMALL)
