"""c4g.bench.gpu_tradeoffs, checked where there is no GPU: its keyframe interpolation against closed
forms (what the engine's rules must reproduce exactly), and one small run of the whole harness on the
CPU whose rows could come out wrong."""

from __future__ import annotations

import json
import math

import pytest
import torch

from c4g.bench import gpu_tradeoffs as gt


def quat_z(angle: float) -> torch.Tensor:
    """w, x, y, z of a turn by `angle` about z."""
    return torch.tensor([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)], dtype=torch.float64)


def sets_at(times: torch.Tensor, n: int = 3) -> torch.Tensor:
    """Canonical sets [K, n, 14] whose channels follow closed forms in t: positions a quadratic,
    scales an exponential, rotations a uniform turn about z, opacity and colour linear."""
    k = len(times)
    g = torch.zeros(k, n, 14, dtype=torch.float64)
    for j in range(n):
        g[:, j, 0] = 1.0 + 0.5 * times + (j + 1) * times**2
        g[:, j, 1] = -times**2
        g[:, j, 2] = 2.0 + j
        g[:, j, 3:6] = (0.01 * torch.exp(0.7 * times))[:, None]
        g[:, j, 6:10] = torch.stack([quat_z(0.9 * float(t)) for t in times])
        g[:, j, 10] = 0.2 + 0.3 * times
        g[:, j, 11:14] = (0.1 * times)[:, None] + 0.1 * j
    return g


def test_interpolation_reproduces_the_rules_closed_forms_between_uneven_keyframes():
    # Bessel tangents are exact for quadratics (the parabola through three keyframes is the path),
    # log-space scales for exponentials, slerp for uniform turns, linear blends for linear channels:
    # so every channel must match its closed form to rounding (1e-10), not to a fitting error.
    kt = torch.tensor([0.0, 0.1, 0.35, 0.4, 1.0], dtype=torch.float64)
    t = torch.linspace(0, 1, 41, dtype=torch.float64)
    got = gt.interpolate(kt, sets_at(kt), t)
    want = sets_at(t)
    # A quaternion and its negation are one rotation.
    sign = torch.sign((got[..., 6:10] * want[..., 6:10]).sum(-1, keepdim=True))
    got[..., 6:10] *= sign
    assert torch.allclose(got, want, atol=1e-10, rtol=0)


def test_interpolation_at_the_keyframes_is_the_keyframes_and_two_keyframes_are_a_chord():
    kt = torch.tensor([0.0, 1.0], dtype=torch.float64)
    sets = sets_at(kt)
    got = gt.interpolate(kt, sets, kt)
    assert torch.allclose(got, sets, atol=1e-12, rtol=0)
    mid = gt.interpolate(kt, sets, torch.tensor([0.5], dtype=torch.float64))[0]
    assert torch.allclose(mid[:, 0:3], (sets[0, :, 0:3] + sets[1, :, 0:3]) / 2, atol=1e-12)  # the chord
    assert torch.allclose(mid[:, 3:6], (sets[0, :, 3:6] * sets[1, :, 3:6]).sqrt(), atol=1e-12)  # geometric mean


def test_slerp_takes_the_shortest_arc_and_blends_nearly_equal_rotations():
    q0, q1 = quat_z(0.0), quat_z(1.2)
    u = torch.tensor(0.25, dtype=torch.float64)
    want = quat_z(0.3)
    assert torch.allclose(gt.slerp(q0, q1, u), want, atol=1e-12)
    assert torch.allclose(gt.slerp(q0, -q1, u), want, atol=1e-12), "the negated quaternion is the same rotation"
    close = gt.slerp(q0, quat_z(1e-5), torch.tensor(0.5, dtype=torch.float64))
    assert torch.allclose(close, quat_z(0.5e-5), atol=1e-12)
    assert torch.isfinite(gt.slerp(q0, q0, u)).all()


def test_placements_are_subsets_of_the_outputs_with_both_ends():
    times = torch.linspace(0, 1, 64).double().numpy()
    for name, idx in gt.placements(times, 0.0, 1 / 30).items():
        assert idx == sorted(set(idx)) and idx[0] == 0 and idx[-1] == 63, name
    counts = {name: len(idx) for name, idx in gt.placements(times, 0.0, 1 / 30).items()}
    assert counts["8 keyframes"] == 8 and counts["4 keyframes"] == 4 and counts["balanced: 16 keyframes (one a context spacing)"] == 16


@pytest.mark.slow
def test_the_harness_runs_on_the_cpu_and_its_reference_rows_are_exact(tmp_path):
    out, md = tmp_path / "rows.json", tmp_path / "table.md"
    assert gt.main(["--device", "cpu", "--small", "--json", str(out), "--markdown", str(md)]) == 0
    result = json.loads(out.read_text())
    rows = {(r["setting"], r["dtype"]): r for r in result["settings"]}
    exact = rows[("exact", "fp32")]
    assert exact["psnr_pooled"] == math.inf and exact["position_error_max"] == 0.0
    # At 12 outputs, 16 uniform keyframes are every output: the keyframed path must give the exact sets.
    assert rows[("balanced: 16 keyframes (one a context spacing)", "fp32")]["psnr_pooled"] == math.inf
    four = rows[("4 keyframes", "fp32")]
    assert four["exact_sets"] == 4 and 0 < four["position_error_max"] and four["psnr_pooled"] < math.inf
    assert all(r["finite"] for r in result["settings"])
    # Reduced precision moves the Gaussians, but by far less than the scene (random weights: ~1 unit).
    assert 0 < rows[("exact", "fp16")]["position_error_max"] < 0.1
    assert rows[("exact", "fp16")]["bytes_per_frame"] * 2 == exact["bytes_per_frame"]
    kept = [r["queries"] for r in result["queries"]]
    assert kept == sorted(kept, reverse=True) and result["queries"][0]["moved_max"] == 0.0, "every query kept is the full decode"
    assert all(r["moved_max"] > 0 for r in result["queries"][1:]), "dropped queries change the others"
    assert "| exact | fp32 |" in md.read_text()


def test_the_harness_refuses_cuda_where_there_is_none():
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    assert gt.main([]) == 2
