"""What the tests share besides fixtures: where the repository and the team's reference data are, and
how the official reference outputs are laid out. The team's data lives in `../shared` beside the
checkout (C4G_SHARED overrides)."""

import os
from pathlib import Path

import numpy as np

PYTHON_ROOT = Path(__file__).resolve().parents[1]
REPO = PYTHON_ROOT.parents[1]
MODELS = REPO / "models"

SHARED = Path(os.environ.get("C4G_SHARED", REPO.parent / "shared"))
OFFICIAL_SMALL_DIR = SHARED / "reference/c4g-official-small"
FIXTURE = MODELS / "fixtures/c4g-small"


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
