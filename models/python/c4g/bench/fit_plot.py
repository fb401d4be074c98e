"""The plot in docs/tradeoffs.md, "Fitting a clip": held-out PSNR on the model's centre crop against
fit time, one colour a clip, from the CSV that `fit/examples/fit_clip.rs` appends to with `--csv`.

    source scripts/env.sh
    cargo run --release -p c4g-fit --example fit_clip -- --name bedroom \\
        --frames ../shared/data/bedroom/frames --fps 30 --presets fast,default --random fast --csv FIT.csv
    python -m c4g.bench.fit_plot --csv FIT.csv --out docs/tradeoffs-fit.png

Each fit is one point (its time: decoding the keyframes, the cover and `fit()`; its held-out crop PSNR);
the feed-forward answer sits at time 0. Dashed lines mark the issue's bars over the feed-forward answer:
+5 dB (`fast`, within 60 s) and +8 dB (`default`, within 5 minutes). The fits' starts (`start:*` rows,
the feed-forward keyframes before any step) are left out: they score as the feed-forward answer does.
When a clip and run appear more than once, the last row counts (a CSV that was appended to again).
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

BARS = ((5.0, "+5 dB"), (8.0, "+8 dB"))
MARKERS = {"fast": "o", "default": "s", "best": "D"}


FIELDS = (
    "clip run steps seconds gaussians static keyframes frames crop_psnr crop_ssim full_psnr full_ssim"
).split()


def read(path: Path) -> dict[str, dict[str, tuple[float, float]]]:
    """{clip: {run: (seconds, crop PSNR)}}, the last row of each clip and run. fit_clip writes rows in
    FIELDS' order without a header, and `#` lines that say what each fit did."""
    out: dict[str, dict[str, tuple[float, float]]] = {}
    with path.open(newline="") as f:
        lines = (line for line in f if line.strip() and not line.startswith("#"))
        for row in csv.DictReader(lines, fieldnames=FIELDS):
            if row["clip"] == "clip" or row["run"].startswith("start:"):
                continue  # a header line; a fit's start
            out.setdefault(row["clip"], {})[row["run"]] = (float(row["seconds"]), float(row["crop_psnr"]))
    return out


def plot(results: dict[str, dict[str, tuple[float, float]]], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5), dpi=120)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for colour, (clip, runs) in zip(colours, sorted(results.items())):
        feed_forward = runs.get("feed-forward")
        for run, (seconds, psnr) in sorted(runs.items(), key=lambda r: r[1][0]):
            random = run.startswith("random:")
            preset = run.removeprefix("random:")
            label = f"{clip}: {'feed-forward' if run == 'feed-forward' else run}"
            ax.scatter(
                seconds,
                psnr,
                color=colour,
                marker="x" if run == "feed-forward" else MARKERS.get(preset, "^"),
                facecolors="none" if random else colour,
                s=48,
                label=label,
            )
            ax.annotate(run, (seconds, psnr), textcoords="offset points", xytext=(5, -11), fontsize=7)
        if feed_forward:
            for gain, name in BARS:
                ax.axhline(feed_forward[1] + gain, color=colour, linestyle="--", linewidth=0.8, alpha=0.6)
                ax.annotate(
                    f"{clip} {name}",
                    (0, feed_forward[1] + gain),
                    textcoords="offset points",
                    xytext=(2, 2),
                    fontsize=7,
                    color=colour,
                )
    ax.axvline(60, color="grey", linewidth=0.6, alpha=0.5)
    ax.axvline(300, color="grey", linewidth=0.6, alpha=0.5)
    ax.set_xlabel("fit time, s (grey: 60 s and 5 min)")
    ax.set_ylabel("held-out PSNR, centre crop, dB")
    ax.set_title("Fitting a clip to its own frames (hollow: random start)")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--csv", type=Path, required=True, help="rows written by fit_clip --csv")
    parser.add_argument("--out", type=Path, default=Path("docs/tradeoffs-fit.png"))
    args = parser.parse_args()
    results = read(args.csv)
    if not results:
        raise SystemExit(f"{args.csv} has no fit rows")
    plot(results, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
