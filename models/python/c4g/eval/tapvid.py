"""TAP-Vid style point-track files and the TAP-Vid metrics, written from the benchmark's definitions.

**The file.** TAP-Vid's DAVIS release is a pickle of a dict per video: `video` [T, H, W, 3] uint8,
`points` [N, T, 2] as (x, y) normalised to [0, 1] by the width and height, `occluded` [N, T] bool.
Ours is an `.npz` with exactly those keys plus `times` [T] (seconds; the service speaks media time)
and `query_frame` [N] (the frame each track is queried at, -1 for a track never queried). A
normalised coordinate is a pixel coordinate divided by the image size, with pixel (i, j) covering
[i, i+1) x [j, j+1): its centre is ((i + 0.5) / W, (j + 0.5) / H), the convention of
`c4g.train.synthetic.render_clip`'s tracks and of the service's tracks endpoint.

Why `.npz` and not pickle: unpickling runs whatever code the file names, so a pickle from a
stranger is a program from a stranger. `load` reads `.npz` with `allow_pickle=False` (arrays only)
and refuses `.pkl` unless the caller passes `allow_pickle=True`, which says "I trust this file"
(the TAP-Vid DAVIS pickle downloaded from its authors, say). Our `.npz` is written with fixed
zip timestamps so the same arrays always give the same bytes (fixtures are checked for that).

**The metrics** (TAP-Vid, Doersch et al. 2022, "query first" mode), per video:
- each track is queried at `query_frame` (by default its first visible frame); only frames *after*
  the query frame are scored (the query frame itself says nothing about a tracker), and only the
  frames `frames` selects (context or interpolated times: see `c4g.eval.protocols`);
- distances are measured after scaling coordinates to a 256 x 256 image, as TAP-Vid does for every
  video whatever its size: a threshold of 1 px means 1/256 of the width and of the height;
- position accuracy at threshold d: of the points visible in the ground truth, the fraction whose
  prediction is within d (strictly closer than d), whatever the tracker says about occlusion;
  `delta_avg` is its mean over d in {1, 2, 4, 8, 16};
- occlusion accuracy: the fraction of scored points whose predicted occlusion flag is right;
- Jaccard at d: TP / (TP + FP + FN) with TP = predicted visible, visible and within d; FP =
  predicted visible and (occluded, or not within d); FN = visible and (predicted occluded, or not
  within d); `average_jaccard` is its mean over the thresholds.
Across videos the benchmark averages the per-video numbers (`mean_over_videos`); a video with no
scored point in a split has NaN there and is left out of that split's mean.
"""

from __future__ import annotations

import io
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

THRESHOLDS = (1, 2, 4, 8, 16)
METRIC_SIZE = 256
KEYS = ("video", "points", "occluded", "times", "query_frame")
# Any fixed date: zip entries carry one, and the file's bytes should depend on its arrays only.
_ZIP_DATE = (2020, 1, 1, 0, 0, 0)


@dataclass
class TrackFile:
    """One video's tracks in TAP-Vid's layout (see the module docstring)."""

    video: np.ndarray  # [T, H, W, 3] uint8
    points: np.ndarray  # [N, T, 2] (x, y) normalised by width and height
    occluded: np.ndarray  # [N, T] bool
    times: np.ndarray  # [T] seconds
    query_frame: np.ndarray  # [N] int, -1: never queried

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.video.shape[2], self.video.shape[1]

    def pixels(self) -> np.ndarray:
        """The points [N, T, 2] in pixels of the video."""
        w, h = self.size
        return self.points * np.array([w, h], np.float64)


def first_visible(occluded: np.ndarray, allowed: np.ndarray | None = None) -> np.ndarray:
    """Per track [N, T], the first frame where it is visible (among `allowed` [T] frames when given);
    -1 when there is none."""
    visible = ~np.asarray(occluded, bool)
    if allowed is not None:
        visible = visible & np.asarray(allowed, bool)[None, :]
    return np.where(visible.any(axis=1), visible.argmax(axis=1), -1)


def make(video: np.ndarray, points_px: np.ndarray, occluded: np.ndarray, times: np.ndarray, query_frame: np.ndarray | None = None) -> TrackFile:
    """A track file from pixel positions [N, T, 2]; queried at each track's first visible frame
    unless `query_frame` says otherwise."""
    video = np.asarray(video)
    if video.dtype != np.uint8 or video.ndim != 4 or video.shape[-1] != 3:
        raise ValueError(f"video must be [T, H, W, 3] uint8, got {video.shape} {video.dtype}")
    h, w = video.shape[1:3]
    occluded = np.asarray(occluded, bool)
    query = first_visible(occluded) if query_frame is None else np.asarray(query_frame)
    return TrackFile(video, np.asarray(points_px, np.float64) / np.array([w, h], np.float64), occluded, np.asarray(times, np.float64), query.astype(np.int64))


def _check(f: TrackFile) -> TrackFile:
    t = f.video.shape[0]
    n = f.points.shape[0]
    if f.points.shape != (n, t, 2) or f.occluded.shape != (n, t) or f.times.shape != (t,) or f.query_frame.shape != (n,):
        raise ValueError(
            f"inconsistent track file: video {f.video.shape}, points {f.points.shape}, occluded {f.occluded.shape}, "
            f"times {f.times.shape}, query_frame {f.query_frame.shape} (want [T,H,W,3], [N,T,2], [N,T], [T], [N])"
        )
    if np.any(np.diff(f.times) <= 0):
        raise ValueError("times must increase strictly")
    return f


def save(path: Path, f: TrackFile) -> None:
    """Writes `f` as a deflated `.npz` whose bytes depend only on the arrays (fixed zip dates)."""
    _check(f)
    arrays = {
        "video": f.video.astype(np.uint8),
        "points": f.points.astype(np.float32),
        "occluded": f.occluded.astype(bool),
        "times": f.times.astype(np.float64),
        "query_frame": f.query_frame.astype(np.int64),
    }
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as z:
        for key in KEYS:
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arrays[key]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            z.writestr(info, buf.getvalue())


def _from_dict(d: dict, fps: float) -> TrackFile:
    video = np.asarray(d["video"])
    occluded = np.asarray(d["occluded"], bool)
    times = np.asarray(d["times"], np.float64) if "times" in d else np.arange(video.shape[0]) / fps
    query = np.asarray(d["query_frame"], np.int64) if "query_frame" in d else first_visible(occluded)
    return _check(TrackFile(video.astype(np.uint8), np.asarray(d["points"], np.float64), occluded, times, query))


def load(path: Path, allow_pickle: bool = False, fps: float = 10.0) -> dict[str, TrackFile]:
    """The videos of a track file, by name: an `.npz` holds one (named after the file, or its folder
    when it is called `tracks.npz`); a TAP-Vid pickle holds a dict of videos (or one video's dict),
    read only with `allow_pickle=True`. Files without `times` get frame index / `fps`; without
    `query_frame`, each track's first visible frame."""
    path = Path(path)
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in ("video", "points", "occluded") if k not in z.files]
            if missing:
                raise ValueError(f"{path}: not a TAP-Vid style file (missing {', '.join(missing)})")
            name = path.parent.name if path.stem == "tracks" else path.stem
            return {name: _from_dict({k: z[k] for k in z.files}, fps)}
    if path.suffix in (".pkl", ".pickle"):
        if not allow_pickle:
            raise ValueError(
                f"{path} is a pickle: loading one runs code the file names. Pass allow_pickle=True "
                "(the runner's --allow-pickle) only for a file you trust, such as TAP-Vid's own release"
            )
        with open(path, "rb") as fh:
            data = pickle.load(fh)  # noqa: S301 - the caller vouched for the file (allow_pickle)
        if isinstance(data, dict) and "video" in data:
            return {path.stem: _from_dict(data, fps)}
        if isinstance(data, dict):
            return {str(k): _from_dict(v, fps) for k, v in data.items()}
        return {f"{path.stem}-{i}": _from_dict(v, fps) for i, v in enumerate(data)}
    raise ValueError(f"{path}: a track file is .npz (or, with allow_pickle, TAP-Vid's .pkl)")


def scored(query_frame: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Which (track, frame) pairs [N, T] count: frames after the track's query frame, among
    `frames` [T]; none for a track without a query."""
    t = len(frames)
    after = np.arange(t)[None, :] > np.asarray(query_frame)[:, None]
    return after & (np.asarray(query_frame)[:, None] >= 0) & np.asarray(frames, bool)[None, :]


def metrics(
    gt_points: np.ndarray,
    gt_occluded: np.ndarray,
    pred_points: np.ndarray,
    pred_occluded: np.ndarray,
    query_frame: np.ndarray,
    frames: np.ndarray | None = None,
) -> dict[str, float]:
    """TAP-Vid's metrics for one video (module docstring). Points are normalised (x, y) [N, T, 2],
    flags [N, T] bool; `frames` [T] selects the frames to score (default all). Returns
    `delta_1` .. `delta_16`, `delta_avg`, `occlusion_accuracy`, `jaccard_1` .. `jaccard_16`,
    `average_jaccard` (NaN where nothing is scored) and the counts `scored` and `visible`."""
    gt_occluded = np.asarray(gt_occluded, bool)
    pred_occluded = np.asarray(pred_occluded, bool)
    t = gt_occluded.shape[1]
    mask = scored(query_frame, np.ones(t, bool) if frames is None else frames)
    visible = ~gt_occluded
    pred_visible = ~pred_occluded
    distance = np.linalg.norm((np.asarray(pred_points) - np.asarray(gt_points)) * METRIC_SIZE, axis=-1)
    n_scored = int(mask.sum())
    n_visible = int((visible & mask).sum())
    nan = float("nan")
    out: dict[str, float] = {}
    deltas, jaccards = [], []
    for d in THRESHOLDS:
        within = distance < d
        correct = within & visible
        delta = (correct & mask).sum() / n_visible if n_visible else nan
        tp = (correct & pred_visible & mask).sum()
        fp = ((~visible | ~within) & pred_visible & mask).sum()
        # TP + FN is every visible point, so TP + FP + FN = visible + FP.
        denominator = n_visible + fp
        jaccard = tp / denominator if denominator else nan
        out[f"delta_{d}"] = float(delta)
        out[f"jaccard_{d}"] = float(jaccard)
        deltas.append(delta)
        jaccards.append(jaccard)
    out["delta_avg"] = float(np.mean(deltas))
    out["average_jaccard"] = float(np.mean(jaccards))
    out["occlusion_accuracy"] = float(((pred_occluded == gt_occluded) & mask).sum() / n_scored) if n_scored else nan
    out["scored"] = n_scored
    out["visible"] = n_visible
    return out


def mean_over_videos(per_video: list[dict[str, float]]) -> dict[str, float]:
    """The benchmark's aggregate: each metric's mean over the videos where it is defined; counts
    are summed, and `videos` says how many videos scored anything."""
    if not per_video:
        return {"videos": 0}
    out: dict[str, float] = {}
    for key in per_video[0]:
        values = np.array([v[key] for v in per_video], np.float64)
        if key in ("scored", "visible"):
            out[key] = int(values.sum())
        else:
            finite = values[np.isfinite(values)]
            out[key] = float(finite.mean()) if len(finite) else float("nan")
    out["videos"] = sum(1 for v in per_video if v["scored"] > 0)
    return out
