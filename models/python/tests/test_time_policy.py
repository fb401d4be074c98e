"""The time policy mirror (the engine's TimePolicy is the one the service runs; engine/src/time.rs)."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from c4g.time_policy import TimeError, normalise


def test_reference_maps_target_to_one():
    ctx, tgt = normalise([0, 2, 4, 6], 3, "reference")
    np.testing.assert_allclose(ctx, np.array([0, 2, 4, 6]) / 3, rtol=1e-6)
    assert tgt == pytest.approx(1.0)


def test_reference_blows_up_at_first_frame():
    ctx, _ = normalise([0, 2, 4, 6], 0, "reference")
    assert ctx.max() > 1e8


@pytest.mark.parametrize("target", [0.0, 1.0, 2.0, 3.0, 6.0])
def test_stable_is_bounded_and_matches_reference_after_one_spacing(target):
    ctx, tgt = normalise([0, 2, 4, 6], target)
    assert np.all(np.isfinite(ctx)) and abs(tgt) <= 3 and np.abs(ctx).max() <= 3
    if target >= 2:
        ref_ctx, ref_tgt = normalise([0, 2, 4, 6], target, "reference")
        np.testing.assert_allclose(ctx, ref_ctx, rtol=1e-6)


def test_single_instant_is_all_zero():
    ctx, tgt = normalise([5.0, 5.0], 5.0)
    assert ctx.tolist() == [0.0, 0.0] and tgt == 0.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -1.0, 7.0])
def test_rejected_targets(bad):
    with pytest.raises(TimeError):
        normalise([0, 2, 4, 6], bad)


finite = st.floats(allow_nan=True, allow_infinity=True, width=64)


@given(st.lists(finite, min_size=1, max_size=8), finite)
def test_stable_never_returns_non_finite(context, target):
    try:
        ctx, tgt = normalise(context, target)
    except TimeError:
        return
    n = len(set(context))
    assert np.all(np.isfinite(ctx)) and np.isfinite(tgt)
    assert np.abs(ctx).max() <= max(n - 1, 0) * (1 + 1e-6)
