"""The time policy mirror (the engine's TimePolicy is the one the service runs; engine/src/time.rs)."""

import json
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from c4g.model.time_policy import TimeError, cross_check_cases, normalise, smallest_gap

from tests.common import MODELS


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


# frame-step: the reference wherever training had inputs (a source frame or more after the first context
# frame), floored at the source frame step s inside [m, m + s).


@pytest.mark.parametrize("target", [0.5, 1.0, 2.0, 3.0, 6.0])
def test_frame_step_equals_reference_from_one_source_frame_on(target):
    ctx, tgt = normalise([0, 2, 4, 6], target, "frame-step", frame_step=1 / 30)
    ref_ctx, ref_tgt = normalise([0, 2, 4, 6], target, "reference")
    assert ctx.tolist() == ref_ctx.tolist() and tgt == ref_tgt


def test_frame_step_at_the_first_frame_sees_the_next_source_frames_context():
    ctx, tgt = normalise([0, 2, 4, 6], 0.0, "frame-step", frame_step=0.5)
    assert ctx.tolist() == [0, 4, 8, 12] and tgt == 0.0
    nxt, nxt_tgt = normalise([0, 2, 4, 6], 0.5, "frame-step", frame_step=0.5)
    assert nxt.tolist() == ctx.tolist() and nxt_tgt == 1.0


def test_frame_step_without_a_step_uses_the_smallest_context_gap():
    for target in [0.0, 0.25, 1.0, 4.0]:
        a = normalise([0, 2, 2.5, 6], target, "frame-step")
        b = normalise([0, 2, 2.5, 6], target, "frame-step", frame_step=0.5)
        assert a[0].tolist() == b[0].tolist() and a[1] == b[1]
    # Evenly spaced context: the smallest gap is the mean spacing, i.e. the stable policy.
    for target in [0.0, 1.0, 3.0]:
        assert normalise([0, 2, 4, 6], target, "frame-step")[0].tolist() == normalise([0, 2, 4, 6], target)[0].tolist()


@pytest.mark.parametrize("step", [0.0, -1.0, math.nan, math.inf])
def test_frame_step_must_be_positive_and_finite(step):
    with pytest.raises(TimeError):
        normalise([0, 2, 4, 6], 1.0, "frame-step", frame_step=step)


@given(st.lists(finite, min_size=1, max_size=8), finite, st.one_of(st.none(), st.floats(1e-6, 1e6)))
def test_frame_step_is_finite_and_bounded_by_span_over_step(context, target, step):
    try:
        ctx, tgt = normalise(context, target, "frame-step", step)
    except TimeError:
        return
    s = step if step is not None else smallest_gap(context)
    bound = 0.0 if s is None else np.float32((max(context) - min(context)) / s)
    assert np.all(np.isfinite(ctx)) and 0 <= tgt <= 1
    assert np.all((ctx >= 0) & (ctx <= bound))


def test_the_engines_cross_check_table_is_what_the_mirror_computes():
    """engine/src/time.rs holds the Rust policies to this table bit for bit; here the mirror is held to it,
    so the two implementations are held to each other."""
    table = json.loads((MODELS / "fixtures/time-policy-cases.json").read_text())
    assert table == cross_check_cases()
    assert {c["policy"] for c in table["cases"]} == {"frame-step", "stable", "reference"}


def test_export_declares_frame_step_for_official_weights_and_the_recipes_policy_for_ours():
    from c4g.package.export import declared_time_policy

    assert declared_time_policy(None) == "frame-step"
    assert declared_time_policy({"steps": 10}) == "frame-step"
    assert declared_time_policy({"time_policy": "stable"}) == "stable"
    with pytest.raises(ValueError):
        declared_time_policy({"time_policy": "blurry"})
