"""The 2D tracking baseline: OpenCV's pyramidal Lucas-Kanade on the input frames.

What a tracker that never leaves the image plane does with the same query points: each query is
followed from its query frame forward to the last frame and backward to the first, frame to frame
(`cv2.calcOpticalFlowPyrLK`), so it can be held against C4G's Gaussian trajectories under the
TAP-Vid metrics (`c4g.eval.tapvid`).

Settings, chosen for 64 x 64 frames before any score was seen, and fixed:
- window 9 x 9 px: about a seventh of the image. OpenCV's default 21 x 21 is made for images ten
  times larger; here it would mix an object with the wall behind it;
- 2 pyramid levels above the image (coarsest 16 x 16, the smallest a 9 x 9 window still fits in):
  motion up to about 4 x the window's half-width between two frames;
- OpenCV's default stopping rule (30 iterations or a step under 0.01 px).
Occlusion: a track is lost at the first step where LK reports failure (status 0), the point
leaves the image, or the forward-backward check fails: tracking the new position back to the
previous frame lands more than `FB_MAX_PX` = 1 input pixel (4 px at TAP-Vid's 256 x 256) from
where it started. A lost track is predicted occluded from there on (in that direction), its
position held at the last good estimate: plain LK cannot find a point again once it has lost it.

Coordinates: ours put pixel (i, j)'s centre at (i + 0.5, j + 0.5); OpenCV puts it at (i, j), so
half a pixel comes off on the way in and goes back on the way out.

Fairness. The service encodes only its context frames. `track` on every input frame is the usual
2D baseline, with more images than the service had; `track_context_only` runs LK over the context
frames alone (as if they were the whole video) and fills the frames between by linear
interpolation of the positions, a point being predicted visible there only when it is at both
neighbouring context frames. `c4g.eval.protocols` reports both, named so.
"""

from __future__ import annotations

import cv2
import numpy as np

WINDOW = (9, 9)
PYRAMID_LEVELS = 2
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
FB_MAX_PX = 1.0


def _grey(frames: np.ndarray) -> list[np.ndarray]:
    return [cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2GRAY) for f in frames]


def _step(a: np.ndarray, b: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points [K, 2] (OpenCV pixels) from image a to image b: (new positions, still good [K])."""
    if len(pts) == 0:
        return pts, np.zeros(0, bool)
    src = pts.reshape(-1, 1, 2).astype(np.float32)
    fwd, status, _ = cv2.calcOpticalFlowPyrLK(a, b, src, None, winSize=WINDOW, maxLevel=PYRAMID_LEVELS, criteria=CRITERIA)
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(b, a, fwd, None, winSize=WINDOW, maxLevel=PYRAMID_LEVELS, criteria=CRITERIA)
    fwd, back = fwd.reshape(-1, 2).astype(np.float64), back.reshape(-1, 2).astype(np.float64)
    h, w = a.shape
    inside = (fwd[:, 0] >= -0.5) & (fwd[:, 0] < w - 0.5) & (fwd[:, 1] >= -0.5) & (fwd[:, 1] < h - 0.5)
    consistent = np.linalg.norm(back - pts, axis=1) <= FB_MAX_PX
    good = status.ravel().astype(bool) & status_back.ravel().astype(bool) & inside & consistent & np.isfinite(fwd).all(1)
    return fwd, good


def track(frames: np.ndarray, query_frame: np.ndarray, query_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """LK tracks over `frames` [T, H, W, 3] uint8 of queries at frame `query_frame` [N] (index into
    frames; -1: not tracked) and pixel `query_xy` [N, 2] (our convention). Returns positions
    [N, T, 2] in pixels and predicted occlusion [N, T] bool (a query is visible at its own frame)."""
    grey = _grey(frames)
    n, t = len(query_frame), len(frames)
    points = np.repeat(np.asarray(query_xy, np.float64)[:, None, :], t, axis=1)
    occluded = np.ones((n, t), bool)
    for q in np.unique(query_frame):
        if q < 0:
            continue
        rows = np.flatnonzero(query_frame == q)
        occluded[rows, q] = False
        for direction in (1, -1):
            alive = rows.copy()
            pts = np.asarray(query_xy, np.float64)[rows] - 0.5
            for frame in range(q + direction, t if direction > 0 else -1, direction):
                # Lost tracks keep their last good position along the rest of the way.
                points[rows, frame] = points[rows, frame - direction]
                nxt, good = _step(grey[frame - direction], grey[frame], pts)
                alive, pts = alive[good], nxt[good]
                points[alive, frame] = pts + 0.5
                occluded[alive, frame] = False
    return points, occluded


def track_context_only(frames: np.ndarray, context: np.ndarray, query_frame: np.ndarray, query_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """LK over the context frames only (`context`: increasing frame indices), each query started
    at the context frame nearest its query frame (the same frame when it is one, as in our
    fixtures), then linear in between. Returns [N, T, 2] and [N, T] over all T frames; frames
    outside the context span take the nearest end's values (they are not scored)."""
    context = np.asarray(context)
    t_all = len(frames)
    nearest = np.where(query_frame >= 0, np.abs(context[None, :] - np.asarray(query_frame)[:, None]).argmin(axis=1), -1)
    sub_points, sub_occluded = track(frames[context], nearest, query_xy)
    points = np.empty((len(query_frame), t_all, 2))
    occluded = np.ones((len(query_frame), t_all), bool)
    for f in range(t_all):
        right = int(np.clip(np.searchsorted(context, f), 0, len(context) - 1))
        left = right if context[right] <= f else max(right - 1, 0)
        if context[left] == context[right]:
            w = 0.0
        else:
            w = (f - context[left]) / (context[right] - context[left])
        points[:, f] = (1 - w) * sub_points[:, left] + w * sub_points[:, right]
        occluded[:, f] = sub_occluded[:, left] | sub_occluded[:, right]
    return points, occluded
