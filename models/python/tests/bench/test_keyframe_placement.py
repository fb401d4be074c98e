"""c4g.bench.keyframe_placement: its cubic is the engine's (exact for constant acceleration on any spacing,
through every keyframe) and its placements are valid keyframe sets."""

import numpy as np

from c4g.bench.keyframe_placement import FPS, bessel_interpolate, placements


def test_the_cubic_reproduces_constant_acceleration_on_uneven_keyframes():
    kt = np.array([0.0, 0.05, 0.3, 0.35, 1.0])
    rng = np.random.default_rng(3)
    p0, v0, a = rng.normal(size=(3, 4, 3))
    path = lambda t: p0 + v0 * t[:, None, None] + 0.5 * a * t[:, None, None] ** 2  # noqa: E731
    t = np.linspace(0, 1, 41)
    np.testing.assert_allclose(bessel_interpolate(kt, path(kt), t), path(t), atol=1e-12)
    # Cubic motion it does not reproduce: the check above could fail.
    cubic = lambda t: path(t) + t[:, None, None] ** 3  # noqa: E731
    assert np.abs(bessel_interpolate(kt, cubic(kt), t) - cubic(t)).max() > 1e-3
    # Two keyframes: the straight line.
    two = bessel_interpolate(kt[[0, -1]], path(kt[[0, -1]]), t)
    ends = path(kt[[0, -1]])
    np.testing.assert_allclose(two, ends[0] + (ends[1] - ends[0]) * t[:, None, None], atol=1e-12)


def test_placements_keep_both_ends_and_start_geometric_spacing_one_source_step_in():
    context = [2 * i / FPS for i in range(16)]
    times = np.linspace(context[0], context[-1], 64)
    for name, idx in placements(times, context, 8).items():
        assert idx == sorted(set(idx)) and idx[0] == 0 and idx[-1] == 63, name
        assert len(idx) == 8, name
    geometric = placements(times, context, 8)["geometric"]
    assert times[geometric[1]] >= context[0] + 1 / FPS
    gaps = np.diff(times[geometric[1:]] - context[0])
    assert np.all(np.diff(gaps) > 0)  # widening, as log spacing does
