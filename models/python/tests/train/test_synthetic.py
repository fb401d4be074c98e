"""The procedural scene generator and the samples cut from it: determinism, disjoint splits, the
model-frame normalisation (both rules), and ground truth that agrees with the frames."""

import numpy as np
import pytest

from c4g.train.dataset import Split, generate, window
from c4g.train.synthetic import FPS, SPLITS, _axis_angle, STATIC_MEDIAN_DEPTH, make_scene, normalise_to_first_camera, render_clip


def test_same_seed_same_scene_and_different_seeds_differ():
    a, b, c = make_scene(7), make_scene(7), make_scene(8)
    for t in (0.0, 0.35, 1.0):
        np.testing.assert_array_equal(a.gaussians(t).means, b.gaussians(t).means)
        np.testing.assert_array_equal(a.camera(t), b.camera(t))
    assert a.gaussians(0.0).means.shape != c.gaussians(0.0).means.shape or not np.allclose(a.gaussians(0.0).means, c.gaussians(0.0).means)


def test_splits_are_disjoint_seed_ranges():
    ranges = sorted(SPLITS.values(), key=lambda r: r.start)
    for lo, hi in zip(ranges, ranges[1:]):
        assert lo.stop <= hi.start


def test_objects_move_and_the_background_does_not():
    scene = make_scene(3)
    moving = scene.dynamic_flags()
    g0, g1 = scene.gaussians(0.0), scene.gaussians(0.5)
    assert 1 <= len(scene.objects) <= 4
    np.testing.assert_array_equal(g0.means[~moving], g1.means[~moving])
    assert np.abs(g0.means[moving] - g1.means[moving]).max() > 1e-3


def _random_poses(rng, n, baseline):
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    for p in poses:
        p[:3, :3] = _axis_angle(rng.normal(size=3), rng.uniform(0, np.pi))
        p[:3, 3] = rng.normal(size=3) * baseline
    return poses


@pytest.mark.parametrize("baseline", [0.7, 0.0])
def test_normalisation_puts_the_first_camera_at_the_origin_and_keeps_every_projection(baseline):
    rng = np.random.default_rng(0)
    poses = _random_poses(rng, 5, baseline)
    if baseline == 0.0:
        poses[:, :3, 3] = 0.0
        poses[:, :3, :3] = poses[0, :3, :3]  # a static camera: one pose throughout
    out, scale = normalise_to_first_camera(poses, 0, 4, median_depth_first=3.0)
    np.testing.assert_allclose(out[0], np.eye(4), atol=1e-12)
    centres = -np.einsum("tji,tj->ti", out[:, :3, :3], out[:, :3, 3])
    if baseline:
        assert np.linalg.norm(centres[4] - centres[0]) == pytest.approx(1.0)
    else:
        assert scale == pytest.approx(STATIC_MEDIAN_DEPTH / 3.0)
    # A world point seen by every camera keeps its image direction: the frame is only rebased and scaled.
    point = rng.normal(size=3)
    point_new = (poses[0][:3, :3] @ point + poses[0][:3, 3]) * scale  # in the first camera's frame, new units
    for old, new in zip(poses, out):
        a = old[:3, :3] @ point + old[:3, 3]
        b = new[:3, :3] @ point_new + new[:3, 3]
        np.testing.assert_allclose(b, a * scale, atol=1e-9)


def test_rendered_ground_truth_agrees_with_the_frames():
    scene = make_scene(11)
    clip = render_clip(scene, np.arange(3) / FPS, 32)
    assert clip.frames.shape == (3, 32, 32, 3) and clip.frames.min() >= 0 and clip.frames.max() <= 1
    assert (clip.alpha > 0.9).mean() > 0.95, "the room surrounds the camera: nearly every pixel is covered"
    assert (clip.depth[clip.alpha > 0.5] > 0).all()
    assert clip.dynamic_mask.any() or not clip.tracks_visible.any()
    # Visible tracked points project inside the image, onto pixels that moving objects cover.
    vis = clip.tracks_visible
    uv = clip.tracks_2d[vis]
    assert ((uv >= 0) & (uv < 32)).all()
    t_idx = np.nonzero(vis)[0]
    px = uv.astype(int)
    near_mask = [clip.dynamic_mask[t, max(0, y - 1) : y + 2, max(0, x - 1) : x + 2].any() for t, (x, y) in zip(t_idx, px)]
    assert np.mean(near_mask) > 0.9


def test_a_split_is_a_function_of_its_name_and_windows_are_in_the_model_frame(tmp_path):
    a = Split.load(generate("validation", 2, tmp_path / "a", processes=1))
    b = Split.load(generate("validation", 2, tmp_path / "b", processes=1))
    np.testing.assert_array_equal(a.frames, b.frames)
    assert list(a.seeds) == list(SPLITS["validation"][:2])
    s = window(a, 0, 2, 3)
    assert list(s.context) == [0, 2, 4] and list(s.targets) == [1, 3]
    np.testing.assert_allclose(s.world_to_camera[0], np.eye(4), atol=1e-9)
    np.testing.assert_allclose(s.times, np.arange(2, 7) / FPS)


# World 2 (the wider training world of c4g-tiny v2), and world 1 left as c4g-tiny was trained on.


def test_world_1_is_the_world_c4g_tiny_was_trained_on_unchanged():
    """Frame means and camera positions of two scenes as they were before world 2 existed (to
    1e-6: the rasterizer's float64 sums on another machine may round their last digits)."""
    before = {
        0: ([0.48685384, 0.48125672, 0.47484493], [0.37479957, 0.3, 0.19880967]),
        7: ([0.47208437, 0.46364573, 0.45690832], [0.57984227, 1.90656175, 3.25258137]),
    }
    for seed, (means, positions) in before.items():
        clip = render_clip(make_scene(seed), np.array([0.0, 0.5, 1.0]), 32)
        np.testing.assert_allclose(clip.frames.mean(axis=(1, 2, 3)), means, atol=1e-6)
        np.testing.assert_allclose(clip.world_to_camera[:, :3, 3].sum(axis=1), positions, atol=1e-6)
    with pytest.raises(ValueError):
        make_scene(0, world=3)


def test_world_2_is_deterministic_and_covers_its_families_motions_and_cameras():
    from c4g.train import synthetic

    a, b = make_scene(11, world=2), make_scene(11, world=2)
    for t in (0.0, 0.45, 1.0):
        np.testing.assert_array_equal(a.gaussians(t).means, b.gaussians(t).means)
        np.testing.assert_array_equal(a.gaussians(t).colors, b.gaussians(t).colors)
        np.testing.assert_array_equal(a.camera(t), b.camera(t))
    motions, cameras, joints, squashy, lit = set(), set(), 0, 0, 0
    for seed in range(60):
        scene = make_scene(seed, world=2)
        cameras.add(scene.camera_motion)
        lit += scene.light != (1.0, 1.0)
        for o in scene.objects:
            motions.add(o.motion)
            joints += o.joint is not None
            squashy += o.deform > 0
    assert motions == set(synthetic.MOTIONS_WORLD2)
    assert cameras == set(synthetic.CAMERA_MOTIONS_WORLD2)
    assert joints > 0 and squashy > 0 and 10 < lit < 50


def test_world_2_motions_do_what_they_say():
    scenes = [make_scene(seed, world=2) for seed in range(80)]
    objects = [(s, o) for s in scenes for o in s.objects]
    # A thrown object never sinks through the floor, and comes down.
    s, thrown = next((s, o) for s, o in objects if o.motion == "ballistic")
    heights = np.array([thrown.transform(t)[1][1] for t in np.linspace(0, s.duration, 101)])
    assert heights.max() <= thrown.motion_params["floor"] + 1e-9 and heights[-1] > heights.min()
    # A stop-and-go object rests between its legs.
    s, stopping = next((s, o) for s, o in objects if o.motion == "stopgo")
    leg = stopping.motion_params["leg"]
    np.testing.assert_allclose(stopping.transform(0.7 * leg)[1], stopping.transform(0.95 * leg)[1], atol=1e-12)
    # A pivoting object keeps its distance to the pivot.
    s, turning = next((s, o) for s, o in objects if o.motion == "pivot")
    pivot = turning.motion_params["pivot"]
    radii = [np.linalg.norm(turning.transform(t)[1] - pivot) for t in (0.0, 0.5, 1.0)]
    np.testing.assert_allclose(radii, radii[0], rtol=1e-9)
    # A jointed object bends: past the joint its Gaussians move against the near part.
    s, jointed = next((s, o) for s, o in objects if o.joint is not None)
    beyond = (jointed.block.means - jointed.joint["pivot"]) @ jointed.joint["along"] > 0
    g = [jointed._bent(jointed.block.means, t)[0] for t in (0.0, 0.3)]
    assert np.abs(g[0][beyond] - g[1][beyond]).max() > 1e-3
    np.testing.assert_array_equal(g[0][~beyond], g[1][~beyond])


def test_world_2_light_changes_colour_and_textures_include_photographs(tmp_path):
    scene = next(s for s in map(lambda k: make_scene(k, world=2), range(40)) if s.light[0] < 0.9 and s.light[1] > 1.0)
    start, end = scene.gaussians(0.0).colors, scene.gaussians(scene.duration).colors
    assert end.mean() > start.mean()
    from c4g.train.synthetic import _photo_texture

    rng = np.random.default_rng(0)
    uv = rng.uniform(0, 1, (500, 2))
    colours = _photo_texture(rng, uv)
    assert colours.shape == (500, 3) and 0 <= colours.min() and colours.max() <= 1 and colours.std() > 0.02
    path = generate("validation", 2, tmp_path, processes=1, world=2)
    assert int(np.load(path)["world"]) == 2
    assert Split.load(path).frames.shape[0] == 2
