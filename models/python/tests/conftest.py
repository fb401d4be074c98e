"""Shared paths. The team's reference data lives in `../shared` beside the checkout (C4G_SHARED overrides)."""

import os
import sys
from pathlib import Path

import numpy as np
import pytest

PYTHON_ROOT = Path(__file__).resolve().parents[1]
REPO = PYTHON_ROOT.parents[1]
sys.path.insert(0, str(PYTHON_ROOT))

SHARED = Path(os.environ.get("C4G_SHARED", REPO.parent / "shared"))
OFFICIAL_SMALL_DIR = SHARED / "reference/c4g-official-small"
FIXTURE = REPO / "models/fixtures/c4g-small"


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
    from c4g.checkpoint import load_checkpoint
    from c4g.config import OFFICIAL_SMALL

    return load_checkpoint(official_small_dir / "c4g_official_small.ckpt", OFFICIAL_SMALL)


def reference_cases(ref) -> list[tuple[str, list[float], list[float]]]:
    """(case, context indices, targets) for every case in the official reference outputs."""
    cases = sorted({k.split("/")[0] for k in ref.files})
    out = []
    for case in cases:
        targets = sorted(
            {float(k.split("/")[1][1:]) for k in ref.files if k.startswith(case + "/t") and k.endswith("/means")}
        )
        out.append((case, ref[f"{case}/index"].astype(float).tolist(), targets))
    return out


def xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    return np.concatenate((q[..., 3:], q[..., :3]), axis=-1)
