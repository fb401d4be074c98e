"""The evaluation-only world (c4g.eval.world) and the generalisation harness (c4g.eval.generalisation)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from c4g.eval import world as eval_world, generalisation
from c4g.eval.held_out import render_gaussians
from c4g.train import synthetic

from tests.common import MODELS

TINY = MODELS / "c4g-tiny"


def test_a_seed_is_always_the_same_clip_and_seeds_differ():
    times = np.array([0.0, 0.8, 1.6])
    a, _, wa = eval_world.render(eval_world.make_scene(3), times, 32)
    b, _, wb = eval_world.render(eval_world.make_scene(3), times, 32)
    c, _, _ = eval_world.render(eval_world.make_scene(4), times, 32)
    assert np.array_equal(a, b) and np.array_equal(wa, wb)
    assert np.abs(a - c).mean() > 0.02


def test_the_world_moves_covers_the_frame_and_spans_its_families():
    seen = {"family": set(), "motion": set(), "camera": set()}
    moving = 0
    for seed in range(40):
        scene = eval_world.make_scene(seed)
        seen["camera"].add(scene.camera_kind)
        for thing in scene.things:
            seen["family"].add(thing.family)
            seen["motion"].add(thing.motion)
        first, last = (scene.gaussians(t)[0] for t in (0.0, scene.duration))
        moving += np.abs(first - last).max() > 0.05
    assert seen["family"] == set(eval_world.OBJECT_FAMILIES)
    assert seen["motion"] == set(eval_world.MOTIONS)
    assert seen["camera"] == set(eval_world.CAMERAS)
    assert moving == 40, "every clip has something that moves"
    rgb, depth, _ = eval_world.render(eval_world.make_scene(0), np.array([0.0]), 32)
    assert (depth > 0).mean() > 0.8 and rgb.std() > 0.05


def test_a_bounce_stays_above_the_ground():
    scene = next(s for s in map(eval_world.make_scene, range(200)) if any(t.motion == "ballistic" for t in s.things))
    thing = next(t for t in scene.things if t.motion == "ballistic")
    heights = [thing.pose(t)[1][1] for t in np.linspace(0, scene.duration, 200)]
    assert max(heights) <= 1.0 - thing.params["radius"] + 1e-9


@pytest.mark.slow
def test_the_harness_scores_the_default_package_and_its_baselines_on_both_worlds():
    package = generalisation.Package(TINY)
    for world in generalisation.WORLDS:
        scores = generalisation.score_clip(package, world, 0, 2)
        assert set(scores) == {*generalisation.METHODS, *generalisation.CEILINGS, *generalisation.RATIOS}
        assert all(0.01 < scores[r] < 100 for r in generalisation.RATIOS)
        for view in ("interpolated", "novel"):
            values = [scores[m][view] for m in generalisation.METHODS + generalisation.CEILINGS[:2]]
            assert all(np.isfinite(v) and 5 < v < 60 for v in values), scores
            # The finer the blocks an oracle averages, the closer to the truth.
            assert scores["true frame in query blocks"][view] > scores["true frame in patches"][view] > scores["mean colour"][view]
        # Two neighbours averaged beat the mean colour at the frames between them.
        assert scores["blend of neighbours"]["interpolated"] > scores["mean colour"]["interpolated"]
        # The context frames are rendered at their own cameras, not from a novel one.
        for row in ("model, reconstructed", "model at the true depth scale"):
            assert 5 < scores[row]["interpolated"] < 60 and scores[row]["novel"] is None
    assert synthetic.FPS == eval_world.FPS


def test_scaling_gaussians_about_the_first_camera_keeps_its_image():
    # What "model at the true depth scale" rests on: positions and sizes scaled together about the
    # camera's centre project to the same ellipses (depth cancels), so only other cameras see it.
    package = generalisation.Package(TINY)
    frames = (np.random.default_rng(0).random((4, 64, 64, 3)) * 255).astype(np.uint8)
    gaussians = package.gaussians(frames, [0.0, 0.2, 0.4, 0.6], [0.1], 0.1)
    scaled = gaussians.copy()
    scaled[..., 0:6] *= 7.0
    identity = np.eye(4)[None]
    before, after = (render_gaussians(torch.from_numpy(g), identity, 64) for g in (gaussians, scaled))
    # Float64 rendering of the same ellipses in another order of magnitude: rounding only.
    np.testing.assert_allclose(after, before, atol=1e-6)
    moved = identity.copy()
    moved[0, 0, 3] = 0.3
    assert np.abs(render_gaussians(torch.from_numpy(scaled), moved, 64) - render_gaussians(torch.from_numpy(gaussians), moved, 64)).max() > 0.05


def test_the_camera_scale_fit_finds_the_factor_that_made_the_frames():
    package = generalisation.Package(TINY)
    frames = (np.random.default_rng(1).random((4, 64, 64, 3)) * 255).astype(np.uint8)
    gaussians = package.gaussians(frames, [0.0, 0.2, 0.4, 0.6], [0.2, 0.4, 0.6], 0.1)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, 3] = [[0.3, 0.0, 0.0], [0.6, 0.1, 0.0], [1.0, 0.1, 0.1]]
    made = poses.copy()
    made[:, :3, 3] *= 0.3
    truth = render_gaussians(torch.from_numpy(gaussians), made, 64)
    factor = generalisation.fit_camera_scale(gaussians, poses, truth, 64)
    # The golden-section search narrows a half-octave bracket by 0.618^12: about 0.002 octave.
    assert abs(np.log2(factor / 0.3)) < 0.01, factor
    # Cameras that do not move fit every factor alike: no evidence, the convention's scale stays.
    assert generalisation.fit_camera_scale(gaussians, np.tile(np.eye(4), (3, 1, 1)), truth, 64) == 1.0


def test_object_ids_cover_the_stage_and_each_thing_where_it_is_seen():
    scene = eval_world.make_scene(5)
    times = np.array([0.0, 0.8])
    ids = eval_world.render_object_ids(scene, times, 64)
    assert ids.shape == (2, 64, 64) and ids.dtype == np.uint8
    assert len(scene.object_ids()) == len(scene.gaussians(0.0)[3])
    assert set(np.unique(ids)) <= set(range(len(scene.things) + 1)) and 0 in ids and ids.max() >= 1
    # Seen from elsewhere (a camera turned away from the things), the masks change.
    cams = np.stack([scene.camera(0.0)] * 2)
    cams[:, :3, 3] += np.array([2.0, 0.0, 0.0])
    assert not np.array_equal(eval_world.render_object_ids(scene, times, 64, cams), ids)
