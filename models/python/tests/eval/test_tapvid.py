"""TAP-Vid style track files and metrics (c4g.eval.tapvid) on cases worked out by hand."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from c4g.eval import tapvid

PX = 1 / tapvid.METRIC_SIZE  # one pixel at TAP-Vid's 256 x 256, in normalised units


def _tracks(n=3, t=6, seed=0):
    rng = np.random.default_rng(seed)
    points = rng.uniform(0.1, 0.9, (n, t, 2))
    occluded = rng.random((n, t)) < 0.3
    occluded[:, 0] = False  # every track queried at frame 0
    return points, occluded


def test_a_perfect_tracker_scores_one_everywhere():
    points, occluded = _tracks()
    m = tapvid.metrics(points, occluded, points, occluded, tapvid.first_visible(occluded))
    for key in ("delta_avg", "occlusion_accuracy", "average_jaccard", *(f"delta_{d}" for d in tapvid.THRESHOLDS)):
        assert m[key] == 1.0, key


def test_predicting_everything_occluded_keeps_positions_and_loses_every_jaccard():
    points, occluded = _tracks()
    query = tapvid.first_visible(occluded)
    m = tapvid.metrics(points, occluded, points, np.ones_like(occluded), query)
    scored = tapvid.scored(query, np.ones(occluded.shape[1], bool))
    # Position accuracy ignores the predicted flags; occlusion accuracy is the share of truly
    # occluded points among those scored; no prediction is visible, so no true positive.
    assert m["delta_avg"] == 1.0
    assert m["occlusion_accuracy"] == pytest.approx((occluded & scored).sum() / scored.sum())
    assert m["average_jaccard"] == 0.0


def test_an_offset_of_three_pixels_passes_thresholds_four_and_up():
    points, occluded = _tracks()
    shifted = points + np.array([3 * PX, 0.0])
    m = tapvid.metrics(points, occluded, shifted, occluded, tapvid.first_visible(occluded))
    assert [m[f"delta_{d}"] for d in tapvid.THRESHOLDS] == [0, 0, 1, 1, 1]
    assert m["delta_avg"] == pytest.approx(0.6)
    # Below the offset every visible prediction is a false positive and every visible point a
    # false negative: J = 0; above it J = 1.
    assert [m[f"jaccard_{d}"] for d in tapvid.THRESHOLDS] == [0, 0, 1, 1, 1]
    assert m["average_jaccard"] == pytest.approx(0.6)
    assert m["occlusion_accuracy"] == 1.0


def test_a_mixed_case_worked_by_hand():
    # One track, 5 frames, queried at frame 0. Truth: visible at 0-3, occluded at 4.
    # Predictions: frame 1 exact; frame 2 five pixels off; frame 3 exact but called occluded;
    # frame 4 called visible.
    gt = np.full((1, 5, 2), 0.5)
    gt_occluded = np.array([[False, False, False, False, True]])
    pred = gt.copy()
    pred[0, 2, 0] += 5 * PX
    pred_occluded = np.array([[False, False, False, True, False]])
    m = tapvid.metrics(gt, gt_occluded, pred, pred_occluded, np.array([0]))
    assert (m["scored"], m["visible"]) == (4, 3)
    assert [m[f"delta_{d}"] for d in tapvid.THRESHOLDS] == pytest.approx([2 / 3, 2 / 3, 2 / 3, 1, 1])
    assert m["delta_avg"] == pytest.approx(0.8)
    assert m["occlusion_accuracy"] == pytest.approx(0.5)
    # d < 8: TP = {1}, FP = {2 (too far), 4 (occluded)}, visible 3 -> 1 / 5.
    # d >= 8: TP = {1, 2}, FP = {4} -> 2 / 4.
    assert [m[f"jaccard_{d}"] for d in tapvid.THRESHOLDS] == pytest.approx([0.2, 0.2, 0.2, 0.5, 0.5])
    assert m["average_jaccard"] == pytest.approx(0.32)


def test_the_query_frame_and_the_frames_before_it_are_not_scored():
    gt = np.full((1, 4, 2), 0.5)
    occluded = np.zeros((1, 4), bool)
    pred = gt.copy()
    pred[0, :2] += 0.3  # wrong at frames 0 and 1
    m = tapvid.metrics(gt, occluded, pred, occluded, np.array([1]))
    assert m["delta_avg"] == 1.0 and m["scored"] == 2
    only_last = np.array([False, False, False, True])
    assert tapvid.metrics(gt, occluded, pred, occluded, np.array([1]), only_last)["scored"] == 1
    never = tapvid.metrics(gt, occluded, pred, occluded, np.array([-1]))
    assert never["scored"] == 0 and np.isnan(never["delta_avg"])


def test_the_first_visible_frame_among_allowed_frames():
    occluded = np.array([[True, False, False], [False, True, True], [True, True, True]])
    assert tapvid.first_visible(occluded).tolist() == [1, 0, -1]
    assert tapvid.first_visible(occluded, np.array([True, False, True])).tolist() == [2, 0, -1]


def test_means_over_videos_skip_videos_with_nothing_scored():
    a = {"delta_avg": 0.5, "scored": 4, "visible": 2}
    b = {"delta_avg": float("nan"), "scored": 0, "visible": 0}
    c = {"delta_avg": 1.0, "scored": 2, "visible": 2}
    m = tapvid.mean_over_videos([a, b, c])
    assert m == {"delta_avg": 0.75, "scored": 6, "visible": 4, "videos": 2}


def test_a_track_file_round_trips_with_the_same_bytes_every_time(tmp_path):
    points, occluded = _tracks(4, 5)
    video = np.random.default_rng(1).integers(0, 256, (5, 8, 10, 3), dtype=np.uint8)
    f = tapvid.make(video, points * np.array([10, 8]), occluded, np.arange(5) / 10)
    tapvid.save(tmp_path / "a.npz", f)
    tapvid.save(tmp_path / "b.npz", f)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    (name, back), = tapvid.load(tmp_path / "a.npz").items()
    assert name == "a"
    np.testing.assert_array_equal(back.video, video)
    np.testing.assert_allclose(back.points, points, atol=1e-6)
    np.testing.assert_array_equal(back.occluded, occluded)
    np.testing.assert_array_equal(back.query_frame, tapvid.first_visible(occluded))
    with np.load(tmp_path / "a.npz") as z:
        assert sorted(z.files) == sorted(tapvid.KEYS)


def test_a_pickle_is_read_only_when_the_caller_trusts_it(tmp_path):
    points, occluded = _tracks(2, 3)
    davis = {"bear": {"video": np.zeros((3, 4, 4, 3), np.uint8), "points": points, "occluded": occluded}}
    path = tmp_path / "tapvid_davis.pkl"
    path.write_bytes(pickle.dumps(davis))
    with pytest.raises(ValueError, match="allow_pickle"):
        tapvid.load(path)
    bear = tapvid.load(path, allow_pickle=True, fps=24)["bear"]
    np.testing.assert_allclose(bear.times, np.arange(3) / 24)
    np.testing.assert_array_equal(bear.query_frame, [0, 0])
