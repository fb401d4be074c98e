"""The plot in docs/time-policy.md: how far the stable and frame-step policies take the decoded Gaussians from
the reference normalisation's, as the target moves through the context span.

    python -m c4g.bench.time_policy_plot --package models/fixtures/c4g-small --out docs/time-policy-deviation.png

The package's own ONNX graphs run on ONNX Runtime (CPU); times are normalised by the Python mirror of the
engine's policies (c4g.model.time_policy). Context frames at 0, 2, 4, 6 s of a 30 fps source (frame step 1/30 s);
the frames are the package's reference frames when it has them (the fixture's), else seeded noise. For each
target: the largest absolute difference from the reference's Gaussians in position, rotation (up to sign)
and colour. Prints the numbers at target 1 s, where the reference is well conditioned and stable is not it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from c4g.model.preprocess import to_model_input
from c4g.model.time_policy import normalise_batch

CONTEXT = [0.0, 2.0, 4.0, 6.0]
FRAME_STEP = 1 / 30
GROUPS = {"position": slice(0, 3), "rotation": slice(6, 10), "colour": slice(11, 14)}
FLOOR = 1e-7  # differences at float rounding (frame-step divides in f64, the reference in f32) and exact zeros


def _frames(package: Path, size: int, count: int) -> np.ndarray:
    ref = package / "reference.safetensors"
    if ref.is_file():
        from safetensors.numpy import load_file

        frames_u8 = load_file(str(ref))["frames_u8"][:count]
        if len(frames_u8) == count and frames_u8.shape[1] == size:
            return to_model_input(frames_u8)
    rng = np.random.default_rng(0)
    return rng.uniform(-1, 1, (count, 3, size, size)).astype(np.float32)


def _session(path: Path):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = 2
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def deviations(package: Path, targets: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
    """{policy: {group: [len(targets)] max abs difference from the reference policy's Gaussians}}, plus
    the reference's own drift: how far its Gaussians are from its own at m + s (the first target training
    had sound inputs for)."""
    manifest = json.loads((package / "model.json").read_text())
    files = manifest["files"]
    frames = _frames(package, manifest["input"]["height"], len(CONTEXT))
    (features,) = _session(package / files["encoder"]).run(None, {"frames": frames})
    decoder = _session(package / files["decoder"])

    def decode(policy: str, at: np.ndarray) -> np.ndarray:
        out = []
        for start in range(0, len(at), 16):
            chunk = at[start : start + 16].tolist()
            ctx, tgt = normalise_batch(CONTEXT, chunk, policy, frame_step=FRAME_STEP)
            (g,) = decoder.run(None, {"features": features, "context_times": ctx, "target_times": tgt})
            out.append(g)
        return np.concatenate(out)

    def distance(a: np.ndarray, b: np.ndarray) -> dict[str, np.ndarray]:
        result = {}
        for name, channels in GROUPS.items():
            x, y = a[..., channels], b[..., channels]
            if name == "rotation":  # q and -q are one rotation
                sign = np.where(np.sum(x * y, axis=-1, keepdims=True) < 0, -1.0, 1.0)
                x = x * sign
            result[name] = np.abs(x - y).max(axis=(-2, -1))
        return result

    reference = decode("reference", targets)
    out = {policy: distance(decode(policy, targets), reference) for policy in ("stable", "frame-step")}
    anchor = decode("reference", np.asarray([CONTEXT[0] + FRAME_STEP]))
    out["reference drift"] = distance(reference, anchor)
    return out


def plot(package: Path, out: Path) -> dict[str, dict[str, float]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m, big_m = CONTEXT[0], CONTEXT[-1]
    span, spacing = big_m - m, (big_m - m) / (len(CONTEXT) - 1)
    linear = np.linspace(m, big_m, 241)
    near = m + np.logspace(-4, np.log10(span), 121)
    targets = np.unique(np.concatenate([linear, near, [m + FRAME_STEP, 1.0]]))
    dev = deviations(package, targets)

    colours = {"stable": "tab:red", "frame-step": "tab:blue"}
    styles = {"position": "-", "rotation": "--", "colour": ":"}
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.6), sharey=True)
    for policy, colour in colours.items():
        for group, style in styles.items():
            y = np.maximum(dev[policy][group], FLOOR)
            left.plot((targets - m) / span, y, style, color=colour, lw=1.4, label=f"{policy}: {group}")
            right.plot(targets - m, y, style, color=colour, lw=1.4)
    drift = np.maximum(dev["reference drift"]["position"], FLOOR)
    inside = targets - m <= FRAME_STEP
    label = "reference vs itself at m + s: position (its blow-up)"
    right.plot((targets - m)[inside], drift[inside], color="0.3", lw=2.2)
    left.plot(((targets - m) / span)[inside], drift[inside], color="0.3", lw=2.2, label=label)

    for ax, scale in ((left, span), (right, 1.0)):
        ax.axvspan(0, spacing / scale, color="tab:red", alpha=0.07, lw=0)
        ax.axvspan(0, FRAME_STEP / scale, color="tab:blue", alpha=0.25, lw=0)
        ax.set_yscale("log")
        ax.grid(True, which="major", alpha=0.3)
    right.set_xscale("log")
    right.set_xlim(1e-4, span)
    left.set_xlim(0, 1)
    left.set_ylim(FLOOR / 2, 3)
    left.set_xlabel("target position in the context span, (target - m) / (M - m)")
    right.set_xlabel("target - m (seconds, log scale)")
    left.set_ylabel("max |Gaussians - reference policy's|")
    right.text(1.3e-4, 2e-5, "[m, m + s): frame-step deviates;\nthe reference blows up here\n(denominator -> 1e-8)", fontsize=8)
    right.text(4.5e-2, 2e-5, "[m, m + h): stable deviates", fontsize=8)
    left.text(0.03, 2e-5, "stable deviates on the\nwhole first interval", fontsize=8, color="tab:red")
    right.axvline(FRAME_STEP, color="tab:blue", lw=0.8)
    right.axvline(spacing, color="tab:red", lw=0.8)
    left.legend(fontsize=7, loc="center right", bbox_to_anchor=(1.0, 0.42))
    fig.suptitle(
        f"{package.name}: context at {', '.join(f'{t:g}' for t in CONTEXT)} s, source frame step s = 1/30 s, "
        f"mean spacing h = {spacing:g} s; differences below {FLOOR:g} (float rounding, or none) drawn at {FLOOR:g}",
        fontsize=10,
    )
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)

    at = int(np.flatnonzero(targets == 1.0)[0])
    return {policy: {group: float(dev[policy][group][at]) for group in GROUPS} for policy in colours}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.bench.time_policy_plot", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--package", type=Path, default=Path("models/fixtures/c4g-small"))
    ap.add_argument("--out", type=Path, default=Path("docs/time-policy-deviation.png"))
    args = ap.parse_args(argv)
    at_one = plot(args.package, args.out)
    print(f"wrote {args.out}")
    for policy, groups in at_one.items():
        print(f"target 1 s, {policy} vs reference: " + ", ".join(f"{g} {v:.3g}" for g, v in groups.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
