"""Recovered cameras against known ones: the acceptance of `POST /v1/clips/{id}/cameras/recover`.

    python -m c4g.eval.cameras --server http://127.0.0.1:8080 models/fixtures/eval [--context 0,2,4,6] [--json out.json]

Per clip folder (`c4g.eval.fixtures`' layout, with its true cameras), two uploads of the same
frames with the same context frames:
- **with** the true cameras (`cameras`): the server maps them into the model's frame (first context
  camera the identity, translations over the largest distance from it) and `GET` shows them: the
  ground truth, in exactly the frame the model reconstructs in;
- **without** cameras, then `POST .../cameras/recover` (photometric alignment of the model's own
  Gaussians), `GET` shows what was recovered.
Scored per context frame after the first (the first is the identity in both, by definition):
- rotation error: the angle of R_recovered R_trueᵀ, degrees;
- translation direction error: the angle between the two camera centres seen from the first
  camera (a monocular model's units are its own, so only directions compare), degrees; frames whose
  true centre is within 1e-6 of the first's are not scored (no direction);
- renders at the recovered and at the true camera of that frame, each against the frame itself
  (PSNR, `c4g.raster.metrics`): the acceptance asks the recovered one within 1 dB.
The clip's two uploads are deleted afterwards.

`--context` picks the context frames (indices into the clip's frames; default the folder's own,
`transforms.json`'s `train_filenames`): c4g-tiny was trained with context frames two apart, so
`0,2,4,6` is where its Gaussians are at their best.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from c4g.raster import metrics

from .protocols import Clip, Service, find_clips, machine


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle of the rotation taking `b` to `a` (3x3), degrees."""
    c = (np.trace(a @ b.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def direction_error_deg(a: np.ndarray, b: np.ndarray) -> float | None:
    """The angle between vectors `a` and `b`, degrees (None when either has no direction)."""
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-6 or nb < 1e-6:
        return None
    return float(np.degrees(np.arccos(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def _matrix(row_major: list[float]) -> np.ndarray:
    return np.asarray(row_major, np.float64).reshape(4, 4)


def _centre(w2c: np.ndarray) -> np.ndarray:
    return -w2c[:3, :3].T @ w2c[:3, 3]


def _with_context(clip: Clip, context: list[int] | None) -> Clip:
    if context is not None:
        clip.context = list(context)
    return clip


def evaluate_clip(service: Service, clip: Clip, refine_focal: bool = False) -> dict:
    """One clip's per-frame errors and PSNRs (see the module doc)."""
    if clip.cameras is None:
        raise ValueError(f"{clip.name}: no true cameras to compare with")
    cameras = clip.cameras
    given = service.upload(clip)
    clip.cameras = None
    try:
        bare = service.upload(clip)
    finally:
        clip.cameras = cameras
    try:
        if given["context_times"] != bare["context_times"]:
            raise RuntimeError(f"{clip.name}: the two uploads have other context frames")
        r = service.http.post(f"/v1/clips/{bare['id']}/cameras/recover", json={"refine_focal": refine_focal})
        recovered = service._ok(r).json()
        truth = given["cameras"]["frames"]
        found = recovered["cameras"]["frames"]
        size = int(np.asarray(clip.tracks.video).shape[1])
        frames = []
        for k, (t, f, fit) in enumerate(zip(truth, found, recovered["fits"])):
            wt, wf = _matrix(t["world_to_camera"]), _matrix(f["world_to_camera"])
            index = int(np.argmin(np.abs(clip.times - t["t"])))
            image = np.asarray(clip.tracks.video[index], np.float64) / 255.0
            at = lambda w2c, k_: service.render(bare["id"], t["t"], w2c, k_, size, size) / 255.0  # noqa: E731
            psnr_true = metrics.psnr(at(wt, t["intrinsics"]), image)
            psnr_found = metrics.psnr(at(wf, f["intrinsics"]), image)
            frames.append(
                {
                    "t": t["t"],
                    "rotation_error_deg": rotation_error_deg(wf[:3, :3], wt[:3, :3]) if k else 0.0,
                    "direction_error_deg": direction_error_deg(_centre(wf), _centre(wt)) if k else None,
                    "psnr_true": psnr_true,
                    "psnr_recovered": psnr_found,
                    "confidence": fit["confidence"],
                    "residual": fit["residual"],
                    "initial_residual": fit["initial_residual"],
                    "focal_recovered": f["intrinsics"]["fx"],
                }
            )
        return {"clip": clip.name, "frames": frames}
    finally:
        service.delete(given["id"])
        service.delete(bare["id"])


def summarise(results: list[dict]) -> dict:
    """Medians and worst cases over every scored frame (the first of each clip excepted)."""
    later = [f for r in results for f in r["frames"][1:]]
    directions = [f["direction_error_deg"] for f in later if f["direction_error_deg"] is not None]
    loss = [f["psnr_true"] - f["psnr_recovered"] for f in later]
    return {
        "frames": len(later),
        "rotation_error_deg": {"median": float(np.median([f["rotation_error_deg"] for f in later])), "max": float(max(f["rotation_error_deg"] for f in later))},
        "direction_error_deg": {"median": float(np.median(directions)), "max": float(max(directions))} if directions else None,
        "psnr_loss_db": {"median": float(np.median(loss)), "max": float(max(loss))},
        "within_1_db": float(np.mean([x <= 1.0 for x in loss])),
    }


def table(results: list[dict]) -> str:
    """Markdown: one row per scored frame."""
    lines = [
        "| clip | t | rotation error ° | translation direction error ° | PSNR at true camera | at recovered | confidence |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        for f in r["frames"][1:]:
            d = f["direction_error_deg"]
            lines.append(
                f"| {r['clip']} | {f['t']:.1f} | {f['rotation_error_deg']:.2f} | {'—' if d is None else f'{d:.1f}'} | "
                f"{f['psnr_true']:.2f} | {f['psnr_recovered']:.2f} | {f['confidence']:.2f} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="+", type=Path)
    parser.add_argument("--server", default="http://127.0.0.1:8080")
    parser.add_argument("--api-key")
    parser.add_argument("--context", help="context frame indices, comma-separated (default: the folder's)")
    parser.add_argument("--refine-focal", action="store_true")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    context = [int(v) for v in args.context.split(",")] if args.context else None
    service = Service(args.server, args.api_key)
    clips = [_with_context(c, context) for c in find_clips(args.paths)]
    results = [evaluate_clip(service, c, args.refine_focal) for c in clips if c.cameras is not None]
    summary = summarise(results)
    print(f"Machine: {machine()}\n")
    print(table(results))
    print("\n" + json.dumps(summary, indent=1))
    if args.json:
        args.json.write_text(json.dumps({"results": results, "summary": summary}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
