"""The float64 rasterizer reference against facts worked out by hand (not by the code under test).

Every Rust rasterizer is held against this reference's saved outputs, so the reference itself is held
against closed forms: the footprint of an isotropic Gaussian (with the ellipse and with the 3DGS tiles),
front-to-back compositing of two layers, the transmittance stop, expected depth, and the skipping rules.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from c4g.raster.reference import ALPHA_MIN, Camera, Margins, render, tiles_3dgs

W, H = 65, 49
F = 40.0


def camera(width=W, height=H, fx=F, fy=F, cx=None, cy=None, view=None) -> Camera:
    # A principal point on a pixel centre puts an on-axis Gaussian's mean exactly on a pixel.
    return Camera(
        fx=fx,
        fy=fy,
        cx=(width / 2 if cx is None else cx),
        cy=(height / 2 if cy is None else cy),
        width=width,
        height=height,
        world_to_camera=np.eye(4) if view is None else view,
    )


def scene(*gaussians):
    """Columns from (position, scale, opacity, colour[, rotation]) tuples."""
    pos = np.array([g[0] for g in gaussians], dtype=np.float64).reshape(-1, 3)
    scl = np.array([g[1] for g in gaussians], dtype=np.float64).reshape(-1, 3)
    opa = np.array([g[2] for g in gaussians], dtype=np.float64).reshape(-1)
    col = np.array([g[3] for g in gaussians], dtype=np.float64).reshape(-1, 3)
    rot = np.array([g[4] if len(g) > 4 else (1, 0, 0, 0) for g in gaussians], dtype=np.float64).reshape(-1, 4)
    return pos, scl, rot, opa, col


def draw(gaussians, cam=None, **kw):
    pos, scl, rot, opa, col = scene(*gaussians)
    return render(pos, scl, rot, opa, col, cam or camera(), **kw)


def test_isotropic_gaussian_facing_the_camera_has_the_analytic_footprint():
    z, s, opacity = 4.0, 0.05, 0.8
    out = draw([((0, 0, z), (s, s, s), opacity, (1, 1, 1))])
    var = (F * s / z) ** 2 + 0.3  # J = diag(f/z) on the axis, plus the low-pass
    cu, cv = W // 2, H // 2  # the pixel whose centre is the mean
    assert out["alpha"][cv, cu] == pytest.approx(opacity, rel=1e-12)
    for dx in range(0, 8):
        d2 = dx * dx / var
        expected = opacity * math.exp(-d2 / 2) if d2 <= 9 and opacity * math.exp(-d2 / 2) >= 1 / 255 else 0.0
        assert out["alpha"][cv, cu + dx] == pytest.approx(expected, rel=1e-12, abs=1e-15)
        assert out["alpha"][cv + dx, cu] == pytest.approx(expected, rel=1e-12, abs=1e-15)
        assert out["alpha"][cv, cu - dx] == pytest.approx(expected, rel=1e-12, abs=1e-15)
    # Beyond 3 sigma nothing, even where opacity · exp(-d²/2) is still above 1/255.
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    d2 = ((xs - W / 2) ** 2 + (ys - H / 2) ** 2) / var
    assert np.all(out["alpha"][d2 > 9] == 0)
    assert np.any((d2 > 9) & (opacity * np.exp(-d2 / 2) >= ALPHA_MIN)), "the 3-sigma cut is exercised"
    assert np.all(out["alpha"][d2 <= 9] > 0)


def test_alpha_saturates_at_0_99():
    out = draw([((0, 0, 2), (0.1, 0.1, 0.1), 1.0, (0.5, 0.5, 0.5))])
    assert out["alpha"].max() == pytest.approx(0.99)


def test_off_axis_isotropic_gaussian_stretches_by_the_jacobian():
    # Isotropic Σ = s² I gives Σ2D = s² J Jᵀ + 0.3 I, with J J ᵀ = (f/z)² [[1 + a², ab], [ab, 1 + b²]],
    # a = x/z, b = y/z (inside the FOV clamp).
    x, y, z, s = 0.6, -0.4, 3.0, 0.15
    a, b = x / z, y / z
    k = (F / z) ** 2 * s * s
    cov = np.array([[k * (1 + a * a) + 0.3, k * a * b], [k * a * b, k * (1 + b * b) + 0.3]])
    inv = np.linalg.inv(cov)
    u, v = F * a + W / 2, F * b + H / 2
    out = draw([((x, y, z), (s, s, s), 0.9, (1, 0, 0))])
    for px, py in [(int(u), int(v)), (int(u) + 2, int(v) - 1), (int(u) - 3, int(v) + 2)]:
        d = np.array([px + 0.5 - u, py + 0.5 - v])
        d2 = d @ inv @ d
        assert d2 <= 9
        assert out["alpha"][py, px] == pytest.approx(0.9 * math.exp(-d2 / 2), rel=1e-9)


def test_anisotropic_rotated_gaussian_matches_the_rotated_covariance():
    # 90 degrees about the view axis swaps the x and y scales on screen.
    q = (math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4))
    z, sx, sy = 5.0, 0.3, 0.05
    out = draw([((0, 0, z), (sx, sy, 0.01), 0.7, (1, 1, 1), q)])
    var_x, var_y = (F * sy / z) ** 2 + 0.3, (F * sx / z) ** 2 + 0.3
    cu, cv = W // 2, H // 2
    assert out["alpha"][cv, cu + 1] == pytest.approx(0.7 * math.exp(-0.5 / var_x), rel=1e-9)
    assert out["alpha"][cv + 3, cu] == pytest.approx(0.7 * math.exp(-0.5 * 9 / var_y), rel=1e-9)


def test_two_layers_composite_front_to_back_whatever_the_input_order():
    front = ((0, 0, 2), (0.5, 0.5, 0.5), 0.6, (1, 0, 0))
    back = ((0, 0, 3), (0.5, 0.5, 0.5), 0.5, (0, 0, 1))
    bg = (0.2, 0.3, 0.4)
    one = draw([front, back], background=bg)
    two = draw([back, front], background=bg)
    for key in one:
        np.testing.assert_array_equal(one[key], two[key])
    c = one["rgb"][H // 2, W // 2]
    t = (1 - 0.6) * (1 - 0.5)
    np.testing.assert_allclose(c, [0.6, 0, 0.5 * 0.4] + t * np.array(bg), rtol=1e-12)
    assert one["alpha"][H // 2, W // 2] == pytest.approx(1 - t)
    assert one["depth"][H // 2, W // 2] == pytest.approx(0.6 * 2 + 0.4 * 0.5 * 3)


def test_exact_depth_ties_go_by_input_index():
    a = ((0, 0, 2), (0.5, 0.5, 0.5), 0.6, (1, 0, 0))
    b = ((0, 0, 2), (0.5, 0.5, 0.5), 0.6, (0, 1, 0))
    c = draw([a, b])["rgb"][H // 2, W // 2]
    np.testing.assert_allclose(c, [0.6, 0.4 * 0.6, 0], rtol=1e-12)


def test_a_pixel_stops_before_the_gaussian_that_would_drop_transmittance_below_1e_4():
    # Alpha 0.5 at the centre: T = 0.5^k; 0.5^13 ≈ 1.2e-4 stays, 0.5^14 ≈ 6.1e-5 would cross, so the
    # 14th and every later one is not drawn there.
    red = [((0, 0, 2 + 0.01 * k), (0.4, 0.4, 0.4), 0.5, (1, 0, 0)) for k in range(13)]
    green = [((0, 0, 2.5 + 0.01 * k), (0.4, 0.4, 0.4), 0.5, (0, 1, 0)) for k in range(5)]
    out = draw(red + green)
    centre = out["rgb"][H // 2, W // 2]
    assert centre[1] == 0.0
    assert centre[0] == pytest.approx(1 - 0.5**13, rel=1e-12)
    assert out["alpha"][H // 2, W // 2] == pytest.approx(1 - 0.5**13, rel=1e-12)
    # Away from the centre the alphas are lower and green does show.
    assert out["rgb"][H // 2, W // 2 + 12, 1] > 0


def test_expected_depth_of_one_opaque_gaussian_is_its_depth():
    z = 3.7
    out = draw([((0, 0, z), (0.3, 0.3, 0.3), 1.0, (1, 1, 1))])
    drawn = out["alpha"] > 0
    assert drawn.sum() > 50
    np.testing.assert_allclose(out["expected_depth"][drawn], z, rtol=1e-12)
    assert np.all(out["expected_depth"][~drawn] == 0)
    assert out["depth"][H // 2, W // 2] == pytest.approx(0.99 * z)


GOOD = ((0.1, 0.05, 3.0), (0.2, 0.1, 0.15), 0.8, (0.9, 0.5, 0.1), (0.9, 0.1, 0.3, 0.2))


@pytest.mark.parametrize("field", ["position", "scale", "rotation", "opacity", "color", "feature"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_parameters_skip_the_gaussian(field, bad):
    pos, scl, rot, opa, col = scene(GOOD, GOOD)
    feats = np.ones((2, 2))
    target = {"position": pos, "scale": scl, "rotation": rot, "color": col, "feature": feats}
    if field == "opacity":
        opa[1] = bad
    else:
        target[field][1, 1] = bad
    out = render(pos, scl, rot, opa, col, camera(), features=feats)
    alone = render(pos[:1], scl[:1], rot[:1], opa[:1], col[:1], camera(), features=feats[:1])
    for key in out:
        np.testing.assert_array_equal(out[key], alone[key])
        assert np.all(np.isfinite(out[key]))


def test_a_zero_rotation_skips_the_gaussian():
    out = draw([GOOD[:4] + ((0, 0, 0, 0),)])
    assert np.all(out["alpha"] == 0)


def test_rotations_need_not_be_normalised():
    unit = draw([GOOD])
    scaled = draw([GOOD[:4] + (tuple(3 * np.array(GOOD[4])),)])
    np.testing.assert_allclose(unit["rgb"], scaled["rgb"], atol=1e-12)


@pytest.mark.parametrize("z", [-1.0, 0.0, 0.0099, 100.01, 1e9])
def test_gaussians_outside_near_and_far_are_skipped(z):
    out = draw([((0, 0, z), (1, 1, 1), 1.0, (1, 1, 1))])
    assert np.all(out["alpha"] == 0) and np.all(out["rgb"] == 0)


@pytest.mark.parametrize("z", [0.0101, 99.99])
def test_gaussians_just_inside_near_and_far_are_drawn(z):
    out = draw([((0, 0, z), (0.01 * z, 0.01 * z, 0.01 * z), 1.0, (1, 1, 1))])
    assert out["alpha"][H // 2, W // 2] == pytest.approx(0.99)


def test_the_camera_pose_moves_gaussians_into_view():
    # Camera at world (0, 0, -5) looking down +z: a Gaussian at the world origin is 5 ahead.
    view = np.eye(4)
    view[2, 3] = 5.0
    out = draw([((0, 0, 0), (0.2, 0.2, 0.2), 0.9, (1, 1, 1))], cam=camera(view=view))
    ref = draw([((0, 0, 5), (0.2, 0.2, 0.2), 0.9, (1, 1, 1))])
    np.testing.assert_allclose(out["alpha"], ref["alpha"], atol=1e-15)
    np.testing.assert_allclose(out["depth"], ref["depth"], rtol=1e-12)


def test_the_fov_clamp_limits_the_jacobian_of_gaussians_far_outside_the_view():
    # x/z = 1.5 is beyond 1.3 · tan(half fov) = 1.3 · W / (2F) = 1.056: J's x/z entry uses 1.056.
    x, z, s = 1.5 * 4.0, 4.0, 1.5
    tan_x = W / (2 * F)
    a = min(x / z, 1.3 * tan_x)
    k = (F / z) ** 2 * s * s
    cov = np.array([[k * (1 + a * a) + 0.3, 0.0], [0.0, k + 0.3]])
    u, v = F * x / z + W / 2, H / 2  # the mean itself stays unclamped
    out = draw([((x, 0, z), (s, s, s), 0.9, (1, 1, 1))])
    px, py = W - 1, H // 2
    d = np.array([px + 0.5 - u, py + 0.5 - v])
    d2 = d @ np.linalg.inv(cov) @ d
    assert d2 < 9
    assert out["alpha"][py, px] == pytest.approx(0.9 * math.exp(-d2 / 2), rel=1e-9)
    # Without the clamp the footprint would be wider: the clamp is what this test sees.
    cov_unclamped = cov.copy()
    cov_unclamped[0, 0] = k * (1 + (x / z) ** 2) + 0.3
    d2_unclamped = d @ np.linalg.inv(cov_unclamped) @ d
    assert abs(d2_unclamped - d2) > 0.1


def test_background_shows_through_the_remaining_transmittance():
    out = draw([((0, 0, 2), (0.2, 0.2, 0.2), 0.5, (1, 1, 1))], background=(0.1, 0.2, 0.3))
    np.testing.assert_allclose(out["rgb"][0, 0], [0.1, 0.2, 0.3])
    t = 1 - out["alpha"]
    np.testing.assert_allclose(out["rgb"][..., 2], out["rgb"][..., 0] + 0.2 * t, atol=1e-12)


def test_features_composite_like_colour_without_background():
    pos, scl, rot, opa, col = scene(GOOD, ((0, 0, 4), (0.3, 0.3, 0.3), 0.7, (0.2, 0.4, 0.6)))
    feats = np.concatenate([col, col[:, :1] * 2], axis=1)
    out = render(pos, scl, rot, opa, col, camera(), features=feats, background=(1, 1, 1))
    t = 1 - out["alpha"]
    np.testing.assert_allclose(out["features"][..., :3], out["rgb"] - t[..., None], atol=1e-12)
    np.testing.assert_allclose(out["features"][..., 3], 2 * out["features"][..., 0], atol=1e-12)


def test_zero_gaussians_give_the_background():
    out = render(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), np.zeros((0, 3)), camera(),
                 background=(0.5, 0.25, 0))
    np.testing.assert_array_equal(out["rgb"], np.broadcast_to([0.5, 0.25, 0], (H, W, 3)))
    assert np.all(out["alpha"] == 0) and np.all(out["expected_depth"] == 0)


def test_zero_scale_is_a_pixel_sized_blob():
    out = draw([((0, 0, 2), (0, 0, 0), 1.0, (1, 1, 1))])
    cu, cv = W // 2, H // 2
    assert out["alpha"][cv, cu + 1] == pytest.approx(math.exp(-0.5 / 0.3))
    assert np.count_nonzero(out["alpha"]) == 9  # d² = r²/0.3 ≤ 9 ⇔ r ≤ 1.64 px: the 3x3 block


def test_margins_report_how_close_a_render_came_to_a_cut():
    m = Margins()
    draw([((0, 0, 4), (0.05, 0.05, 0.05), 0.8, (1, 1, 1))], margins=m)
    var = (F * 0.05 / 4) ** 2 + 0.3
    # Pixel distances² on the grid are integers; d² = r²/var, the closest to 9.
    r2 = np.array([dx * dx + dy * dy for dx in range(-8, 9) for dy in range(-8, 9)])
    assert m.d2 == pytest.approx(np.abs(r2 / var - 9)[np.abs(r2 / var - 9) < 1].min())
    assert m.transmittance > 0 and m.alpha > 0 and m.near_far > 0


@settings(max_examples=25, deadline=None)
@given(st.permutations(list(range(6))), st.integers(0, 2**31 - 1))
def test_input_order_does_not_matter(perm, seed):
    rng = np.random.default_rng(seed)
    pos = rng.uniform([-1, -1, 2], [1, 1, 4], (6, 3))
    scl = rng.uniform(0.05, 0.4, (6, 3))
    rot = rng.normal(size=(6, 4))
    opa = rng.uniform(0, 1, 6)
    col = rng.uniform(0, 1, (6, 3))
    a = render(pos, scl, rot, opa, col, camera(33, 25))
    p = np.array(perm)
    b = render(pos[p], scl[p], rot[p], opa[p], col[p], camera(33, 25))
    for key in a:
        np.testing.assert_allclose(a[key], b[key], atol=1e-12)


# ---- the 3DGS footprint --------------------------------------------------------------------------
# An isotropic Gaussian on the axis of a 128 x 128 camera (f = 64, principal point (77.4, 64)): var =
# (64 · 0.4 / 4)² + 0.3 = 41.26, sigma = 6.42 px. 3DGS: lambda = var + sqrt(0.1) (the discriminant is 0,
# floored), 3 sqrt(lambda) = 19.34, r = 20; p = (76.9, 63.5), so its tiles are x in [floor(56.9 / 16),
# floor(111.9 / 16)) = [3, 6) and y in [floor(43.5 / 16), floor(98.5 / 16)) = [2, 6).
BIG_VAR = (64 * 0.4 / 4) ** 2 + 0.3


def big(footprint, **kw):
    cam = camera(width=128, height=128, fx=64.0, fy=64.0, cx=77.4, cy=64.0)
    return draw([((0, 0, 4), (0.4, 0.4, 0.4), 0.9, (1, 1, 1))], cam=cam, footprint=footprint, **kw)


def test_the_3dgs_tiles_of_an_isotropic_gaussian_are_worked_out_by_hand():
    raw, rect = tiles_3dgs(np.array([77.4, 64.0]), BIG_VAR * np.eye(2), 128, 128)
    assert raw == pytest.approx(3 * math.sqrt(BIG_VAR + math.sqrt(0.1)), rel=1e-12)
    assert rect == (3, 2, 6, 6)
    # Off screen to the left and right: the ends clamp to the grid, and an empty range is empty.
    assert tiles_3dgs(np.array([-500.0, 64.0]), BIG_VAR * np.eye(2), 128, 128)[1][::2] == (0, 0)
    assert tiles_3dgs(np.array([700.0, 64.0]), BIG_VAR * np.eye(2), 128, 128)[1][::2] == (8, 8)


def test_the_3dgs_footprint_draws_every_pixel_of_its_tiles_down_to_1_255_and_nothing_outside():
    out = big("3dgs")
    ys, xs = np.mgrid[0:128, 0:128]
    d2 = ((xs + 0.5 - 77.4) ** 2 + (ys + 0.5 - 64.0) ** 2) / BIG_VAR
    expected = 0.9 * np.exp(-d2 / 2)
    in_tiles = (xs >= 48) & (xs < 96) & (ys >= 32) & (ys < 96)
    drawn = in_tiles & (expected >= ALPHA_MIN)
    np.testing.assert_allclose(out["alpha"][drawn], expected[drawn], rtol=1e-12)
    assert np.all(out["alpha"][~drawn] == 0)
    # The fringe beyond 3 sigma is drawn, and the ellipse cuts it.
    fringe = drawn & (d2 > 9)
    assert fringe.sum() > 100
    assert np.all(big("ellipse")["alpha"][fringe] == 0)
    # Pixel column 96 lies inside the square p ± r (p + r = 96.9) but not inside the tiles: within 3
    # sigma on the centre row, the ellipse draws it and 3DGS does not.
    assert d2[64, 96] < 9 and expected[64, 96] > ALPHA_MIN
    assert out["alpha"][64, 96] == 0 and big("ellipse")["alpha"][64, 96] > 0


def test_the_3dgs_footprint_draws_what_the_ellipse_draws_inside_3_sigma_and_its_tiles():
    tiles, ellipse = big("3dgs"), big("ellipse")
    both = (tiles["alpha"] > 0) & (ellipse["alpha"] > 0)
    assert both.sum() > 1000
    np.testing.assert_array_equal(tiles["rgb"][both], ellipse["rgb"][both])


def test_an_unknown_footprint_is_refused():
    with pytest.raises(ValueError, match="footprint"):
        big("gsplat")


def test_margins_report_how_close_3dgs_tiles_came_to_moving():
    m = Margins()
    big("3dgs", margins=m)
    # Ends p - r = 56.9, p + r + 15 = 111.9 (x), 43.5, 98.5 (y): 7.1, 0.1, 4.5 and 2.5 from a multiple of
    # 16; and 3 sqrt(lambda) is 0.66 from an integer (counted: 111.9 lies within a pixel of 112).
    raw = 3 * math.sqrt(BIG_VAR + math.sqrt(0.1))
    assert m.tiles == pytest.approx(min(0.1, abs(raw - round(raw))), abs=1e-9)
    assert m.d2 == math.inf and 0 < m.power < math.inf
    assert Margins().tiles == math.inf
    e = Margins()
    big("ellipse", margins=e)
    assert e.tiles == math.inf and e.d2 < math.inf
