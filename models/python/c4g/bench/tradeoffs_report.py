"""docs/tradeoffs.md and its plot, from the trade-off harness's results.

    cargo bench -p c4g-engine --bench tradeoffs          # writes target/tradeoffs.json
    python -m c4g.bench.tradeoffs_report --results target/tradeoffs.json --out docs

Reads the JSON the harness (`engine/benches/tradeoffs.rs`) wrote, marks the Pareto front of time per
output frame against quality (a setting is on it when no other setting is at least as fast and at
least as good, and strictly one of the two), proposes the presets `exact`, `balanced` and `fast` as
points on that front by the rules in `PRESET_RULES`, and writes `tradeoffs.md` and `tradeoffs.png`
into `--out`.

Quality is PSNR in dB, two ways: against ground truth (mean over the test clips' interpolated targets
and novel views) and against the exact output (the baseline's renders at the same resolution; `null` in
the JSON when the renders are identical, which counts as the best there is). The *loss* of a setting is
the exact baseline's ground-truth PSNR minus its own.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path

BASELINE = "exact"
# Presets are request options (keyframes, pruning, wire precision): chosen among the settings at the
# baseline's resolution, context frames and package precision, which a request does not change.
# Count keyframes are left out of them: a count is the same whatever the range's length, so a preset
# written as a count would mean coarser keyframes on every longer clip.
PRESET_POOL = {"resolution": 64, "context_frames": 4, "precision": "f32"}
PRESET_KEYFRAME_MODES = ("exact", "every", "adaptive")


@dataclass(frozen=True)
class Rule:
    name: str
    max_loss_db: float | None  # None: the baseline itself
    min_vs_exact_db: float = 0.0
    why: str = ""


# Why fidelity bounds beside the loss: c4g-tiny's own error (about 21 dB against ground truth) hides
# what keyframes, pruning and f16 add (the whole sweep at 64 px and T = 4 is within a few hundredths of
# a dB there), so a loss bound alone would call every setting equal. The bounds on PSNR against the
# exact renders are in 8-bit terms: 48.1 dB = 20 log10(255) is an RMS difference of one level, 40 dB
# of 1 % of the range (2.55 levels).
PRESET_RULES = (
    Rule("exact", None, why="the baseline: every set decoded, all Gaussians, f32 wire"),
    Rule("balanced", 0.1, 48.1, why="the fastest losing at most 0.1 dB against ground truth, within one 8-bit level RMS of the exact renders (≥ 48.1 dB)"),
    Rule("fast", 0.5, 40.0, why="the fastest losing at most 0.5 dB against ground truth (the issue's bound), within 1 % RMS of the exact renders (≥ 40 dB)"),
)
# Times within this fraction of the fastest qualifying setting's are a tie (run-to-run noise on a
# shared machine is larger); a tie goes to the one closest to exact.
TIME_TIE = 0.05
STREAM_TARGET_SETS_PER_S = 1000.0
# What the service serves for each preset (`service/src/sets/quality.rs`: keyframes every 1 and 1.5 context
# spacings, `fast` also pruning at 0.5 px; the wire precision is the request's own `precision`), as
# the sweep names those settings on the test clips (context frames 0.2 s apart) with the f16 wire.
# The page says how each does on this run against its rule, so a remade page shows when a new model or
# machine moves the rule's pick away from what is served; changing what is served is quality.rs's.
SERVED_PRESETS = {
    "balanced": "every 0.2 s",
    "fast": "every 0.3 s + prune 0.5 px + f16 wire",
}


def frames_to_amortise(row: dict, target: float = STREAM_TARGET_SETS_PER_S) -> float | None:
    """Frames a stream over one clip needs before its once-per-clip pruning analysis leaves the rate at
    `target` sets a second: n / (n / rate + analysis) >= target. 0 without an analysis; None when the
    producing rate alone is below the target."""
    analysis_s = (row.get("analysis_ms_per_clip") or 0.0) / 1e3
    per_set = 1.0 / row["sets_per_s"]
    if per_set >= 1.0 / target:
        return None
    return math.ceil(analysis_s / (1.0 / target - per_set))


def vs_exact(row: dict) -> float:
    """PSNR against the exact output; identical renders are +inf."""
    value = row["vs_exact"]["psnr"]
    return math.inf if value is None else float(value)


def gt_psnr(row: dict) -> float:
    return float(row["gt"]["psnr"])


def pareto(rows: list[dict], *qualities, time_key: str = "ms_per_frame") -> list[dict]:
    """The rows no other row dominates (at least as fast and at least as good in every quality, strictly
    better in one of them), fastest first."""

    def key(r):
        return (-r[time_key], *(q(r) for q in qualities))

    front = []
    for r in rows:
        kr = key(r)
        dominated = any(
            o is not r and all(a >= b for a, b in zip(key(o), kr)) and any(a > b for a, b in zip(key(o), kr))
            for o in rows
        )
        if not dominated:
            front.append(r)
    return sorted(front, key=lambda r: r[time_key])


def baseline(rows: list[dict]) -> dict:
    for r in rows:
        if r["name"] == BASELINE:
            return r
    raise ValueError(f"the results hold no {BASELINE!r} row to compare with")


def loss_db(row: dict, base: dict) -> float:
    return gt_psnr(base) - gt_psnr(row)


def in_pool(row: dict, modes=PRESET_KEYFRAME_MODES) -> bool:
    return all(row[k] == v for k, v in PRESET_POOL.items()) and row["keyframes"]["mode"] in modes


def served_verdicts(rows: list[dict], presets: dict[str, dict], served=SERVED_PRESETS, rules=PRESET_RULES, tie: float = TIME_TIE) -> dict[str, dict]:
    """{preset: {"row", "within_bounds", "within_tie"}} for each served setting the sweep measured: whether it
    meets its rule's loss and fidelity bounds on this run, and whether its time is within `tie` of the
    rule's pick's (or faster)."""
    by_name = {r["name"]: r for r in rows}
    base = baseline(rows)
    out = {}
    for rule in rules:
        r = by_name.get(served.get(rule.name, ""))
        pick = presets.get(rule.name)
        if r is None or rule.max_loss_db is None:
            continue
        out[rule.name] = {
            "row": r,
            "within_bounds": loss_db(r, base) <= rule.max_loss_db and vs_exact(r) >= rule.min_vs_exact_db,
            "within_tie": pick is not None and r["ms_per_frame"] <= pick["ms_per_frame"] * (1 + tie),
        }
    return out


def choose_presets(rows: list[dict], rules=PRESET_RULES, tie: float = TIME_TIE, modes=PRESET_KEYFRAME_MODES) -> dict[str, dict]:
    """{preset: row}: for each rule the fastest pool row within its loss and fidelity bounds (the
    baseline for a rule without a bound), rows within `tie` of the fastest's time counting as tied and
    the tie going to the highest PSNR against exact. A rule no row meets is left out."""
    base = baseline(rows)
    presets = {}
    for rule in rules:
        if rule.max_loss_db is None:
            presets[rule.name] = base
            continue
        ok = [
            r
            for r in rows
            if in_pool(r, modes) and loss_db(r, base) <= rule.max_loss_db and vs_exact(r) >= rule.min_vs_exact_db
        ]
        if ok:
            fastest = min(r["ms_per_frame"] for r in ok)
            tied = [r for r in ok if r["ms_per_frame"] <= fastest * (1 + tie)]
            presets[rule.name] = max(tied, key=lambda r: (vs_exact(r), -r["ms_per_frame"]))
    return presets


# ----------------------------------------------------------------------------------------------------
# Writing


def _db(v: float | None) -> str:
    if v is None or v == math.inf:
        return "identical"
    return f"{v:.2f}"


def _keyframes(row: dict) -> str:
    k = row["keyframes"]
    return {
        "exact": lambda: "exact",
        "every": lambda: f'`{{"every_s": {k["seconds"]}}}`',
        "count": lambda: f'`{{"count": {k["n"]}}}`',
        "adaptive": lambda: f'`{{"tolerance": {k["tolerance"]}}}`',
    }[k["mode"]]()


def _prune(row: dict) -> str:
    p = row["prune"]
    return "off" if p is None else f'{p["contribution_floor"]:g} px (opacity {p["opacity_floor"]:.4f})'


def _marks(row: dict, fronts: dict[str, list[dict]], presets: dict[str, dict]) -> str:
    marks = [name for name, front in fronts.items() if any(r is row for r in front)]
    names = [p for p, r in presets.items() if r is row]
    text = ", ".join(f"front ({m})" for m in marks)
    if names:
        text = f"**{' / '.join(names)}**" + (", " + text if text else "")
    return text


def table(rows: list[dict], fronts, presets) -> list[str]:
    base = baseline(rows)
    out = [
        "| setting | knob | ms / frame | decode share | sets/s | exact decodes | Gaussians | bytes / frame f32 · f16 | peak MiB (rise) | GT PSNR interp · novel | GT SSIM | loss dB | vs exact PSNR (worst frame) | vs exact SSIM | preset, front |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        rise = max(r["peak_rise_mib"] or 0.0, 0.0)
        peak = r["peak_rss_mib"]
        out.append(
            "| {name} | {knob} | {ms:.2f} | {share:.0%} | {sps:,.0f} | {dec:g} | {g:.0f} | {b32:,.0f} · {b16:,.0f} | {peak} ({rise:.0f}) | {gi:.2f} · {gn:.2f} | {ssim:.3f} | {loss:+.2f} | {ve} ({vw}) | {vs:.4f} | {marks} |".format(
                name=r["name"],
                knob=r["knob"],
                ms=r["ms_per_frame"],
                share=r["decode_share"],
                sps=r["sets_per_s"],
                dec=round(r["exact_decodes_per_clip"], 1),
                g=r["gaussians"],
                b32=r["bytes_per_frame_f32"],
                b16=r["bytes_per_frame_f16"],
                peak="—" if peak is None else f"{peak:.0f}",
                rise=rise,
                gi=r["gt"]["psnr_interpolated"],
                gn=r["gt"]["psnr_novel"],
                ssim=r["gt"]["ssim"],
                loss=loss_db(r, base),
                ve=_db(r["vs_exact"]["psnr"]),
                vw=_db(r["vs_exact"]["psnr_worst_frame"]),
                vs=r["vs_exact"]["ssim"],
                marks=_marks(r, fronts, presets),
            )
        )
    return out


def _short(row: dict) -> str:
    return row["name"].replace(" + ", "+").replace(" package", "").replace(" wire", "w").replace("adaptive ", "tol ")


def _preset_points(presets: dict[str, dict]) -> list[tuple[dict, list[str]]]:
    """Each preset's row once, with every preset name it carries."""
    points: list[tuple[dict, list[str]]] = []
    for name, r in presets.items():
        for row, names in points:
            if row is r:
                names.append(name)
                break
        else:
            points.append((r, [name]))
    return points


def _place_labels(ax, labels, points) -> None:
    """Annotates each (text, x, y, style) at the first of a few offsets around its point whose box
    overlaps no label placed before it, no other point and nothing outside the axes (else the first)."""
    fig = ax.figure
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    marks = [ax.transData.transform((x, y)) for x, y in points]
    placed = []
    near = [(7, 4), (7, -11), (-7, 4), (-7, -11), (7, 14), (7, -21), (-7, 14), (-7, -21)]
    # Farther out, with a leader line to the point.
    far = [(dx, dy) for dy in (30, -38, 48, -56, 66, -74) for dx in (20, -20, 60, -60)]
    offsets = near + far

    def clear(box, own):
        if box.x0 < frame.x0 or box.x1 > frame.x1 or box.y0 < frame.y0 or box.y1 > frame.y1:
            return False
        if any(box.overlaps(p) for p in placed):
            return False
        return not any(box.x0 - 3 < mx < box.x1 + 3 and box.y0 - 3 < my < box.y1 + 3 for mx, my in marks if (mx, my) != own)

    for text, x, y, style in labels:
        own = tuple(ax.transData.transform((x, y)))
        chosen = None
        for dx, dy in offsets:
            leader = {"arrowprops": {"arrowstyle": "-", "color": "grey", "linewidth": 0.6, "shrinkA": 0, "shrinkB": 4}} if (dx, dy) in far else {}
            t = ax.annotate(text, (x, y), xytext=(dx, dy), textcoords="offset points", ha="left" if dx > 0 else "right", zorder=6, **leader, **style)
            box = t.get_window_extent(renderer)
            if clear(box, own):
                chosen = box
                break
            t.remove()
        if chosen is None:
            t = ax.annotate(text, (x, y), xytext=offsets[0], textcoords="offset points", zorder=6, **style)
            chosen = t.get_window_extent(renderer)
        placed.append(chosen)


def plot(rows: list[dict], fronts, presets, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    finite = [vs_exact(r) for r in rows if vs_exact(r) != math.inf]
    ceiling = (max(finite) if finite else 60.0) + 6.0
    knobs = sorted({r["knob"] for r in rows})
    markers = dict(zip(knobs, "o^sDvP*Xh<>"))
    colours = {64: "tab:blue", 128: "tab:orange", 256: "tab:red"}
    fig, axes = plt.subplots(1, 2, figsize=(15, 7.2), constrained_layout=True)
    panels = [
        ("vs exact", lambda r: min(vs_exact(r), ceiling), "PSNR against the exact output (dB)"),
        ("vs ground truth", gt_psnr, "PSNR against ground truth (dB), interpolated and novel views"),
    ]
    for ax, (key, q, ylabel) in zip(axes, panels):
        for r in rows:
            ax.scatter(r["ms_per_frame"], q(r), marker=markers[r["knob"]], s=46, color=colours.get(r["resolution"], "grey"), edgecolors="black", linewidths=0.4, alpha=0.85, zorder=3)
        front = fronts[key]
        xs = [r["ms_per_frame"] for r in front]
        ys = [q(r) for r in front]
        # The front as a staircase: what the fastest setting at least this good costs.
        ax.step(xs, ys, where="post", color="black", linewidth=1.0, alpha=0.6, zorder=2, label="Pareto front")
        labels = []
        for r, names in _preset_points(presets):
            ax.scatter(r["ms_per_frame"], q(r), s=260, facecolors="none", edgecolors="green", linewidths=2.0, zorder=4)
            text = " / ".join(names) + ("" if r["name"] in names else f": {_short(r)}")
            labels.append((text, r["ms_per_frame"], q(r), {"fontsize": 9, "color": "green", "fontweight": "bold"}))
        ringed = [r for r, _ in _preset_points(presets)]
        labels += [(_short(r), r["ms_per_frame"], q(r), {"fontsize": 7, "color": "black"}) for r in front if not any(r is p for p in ringed)]
        ax.set_xscale("log")
        plain = FuncFormatter(lambda v, _: f"{v:g}")
        ax.xaxis.set_major_formatter(plain)
        ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if f"{v:g}"[0] in "25" else ""))
        ax.set_xlabel("time per output frame: decode + render, ms (log scale)")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        if key == "vs exact":
            ax.axhline(ceiling, color="grey", linestyle=":", linewidth=0.8)
            ax.text(ax.get_xlim()[0], ceiling, "  identical to exact", va="bottom", fontsize=8, color="grey")
            ax.set_ylim(top=ceiling + 3)
        ax.set_title(f"quality {key} against time")
        _place_labels(ax, labels, [(r["ms_per_frame"], q(r)) for r in rows])
    handles = [plt.Line2D([], [], marker=markers[k], linestyle="", color="grey", markeredgecolor="black", label=k) for k in knobs]
    handles += [plt.Line2D([], [], marker="o", linestyle="", color=c, label=f"{res} px") for res, c in colours.items()]
    handles += [plt.Line2D([], [], color="black", alpha=0.6, label="Pareto front"), plt.Line2D([], [], marker="o", linestyle="", markerfacecolor="none", markeredgecolor="green", markersize=12, label="preset")]
    fig.legend(handles=handles, loc="outside right center", fontsize=8)
    fig.suptitle("c4g-tiny: speed against accuracy, one setting a point (engine/benches/tradeoffs.rs)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _describe(row: dict) -> str:
    return f"keyframes {_keyframes(row)}, pruning {_prune(row)}, {row['wire']} wire"


def _by_name(rows: list[dict]) -> dict[str, dict]:
    return {r["name"]: r for r in rows}


def findings(rows: list[dict]) -> list[str]:
    """Sentences computed from the rows: each is said only when its rows are in the results, with their
    numbers, so the text stays true to the data it is written from."""
    by = _by_name(rows)
    base = baseline(rows)
    out = []
    t0 = base["ms_per_frame"]

    def speed(r):
        return f"{t0 / r['ms_per_frame']:.1f}× exact's speed"

    out.append(f"**Exact** takes {t0:.2f} ms an output frame at 64 px, {base['decode_share']:.0%} of it decoding "
               f"({base['sets_per_s']:,.0f} sets/s): at this size the decoder is the cost, and the render "
               f"({base['render_ms_per_frame']:.2f} ms) a small part.")
    same = [r for r in rows if r["keyframes"]["mode"] == "exact" and r["context_frames"] == base["context_frames"]
            and r["precision"] == base["precision"]]
    if len(same) > 1:
        lo = min(r["decode_ms_per_frame"] for r in same)
        hi = max(r["decode_ms_per_frame"] for r in same)
        out.append(f"**The noise:** the {len(same)} settings that decode the same 64 sets exactly (f32, T=4: "
                   + ", ".join(r["name"] for r in same)
                   + f") took {lo:.2f}–{hi:.2f} ms a set to produce. Read differences in time smaller than that spread "
                   "(about ×" f"{hi / lo:.1f}) as the machine's load, not the setting.")
    keyed = [r for r in rows if r["knob"] == "keyframes"]
    if keyed:
        fastest = min(keyed, key=lambda r: r["ms_per_frame"])
        closest = max(keyed, key=vs_exact)
        out.append(f"**Keyframes** are the lever: {fastest['name']} runs at {speed(fastest)} "
                   f"({fastest['exact_decodes_per_clip']:g} decodes a clip, {_db(fastest['vs_exact']['psnr'])} dB from exact), "
                   f"{closest['name']} at {speed(closest)} ({closest['exact_decodes_per_clip']:g} decodes, "
                   f"{_db(closest['vs_exact']['psnr'])} dB).")
        if "every 0.1 s" in by and "count 8" in by:
            a, b = by["every 0.1 s"], by["count 8"]
            out[-1] += (f" Where keyframes sit matters as much as how many: every 0.1 s ({a['exact_decodes_per_clip']:g} keyframes, "
                        f"on the context frames among them) is {_db(a['vs_exact']['psnr'])} dB from exact, count 8 "
                        f"({b['exact_decodes_per_clip']:g}, across them) {_db(b['vs_exact']['psnr'])} dB.")
    pruned = [by[n] for n in ("prune 0.5 px", "prune 2 px") if n in by]
    if pruned:
        parts = [f"{r['prune']['contribution_floor']:g} px keeps {r['gaussians']:.0f} of {base['gaussians']:.0f} Gaussians "
                 f"({r['bytes_per_frame_f32'] / base['bytes_per_frame_f32']:.0%} of the bytes), {_db(r['vs_exact']['psnr'])} dB "
                 f"from exact, novel view {r['gt']['psnr_novel'] - base['gt']['psnr_novel']:+.2f} dB against ground truth"
                 for r in pruned]
        text = "**Pruning**: " + "; ".join(parts) + ". "
        res = [by[n] for n in ("prune 0.5 px + 128 px", "prune 0.5 px + 256 px") if n in by]
        if res:
            text += "At higher resolutions the same floor in pixels is stricter (the pixels are smaller): " + ", ".join(
                f"{r['resolution']} px keeps {r['gaussians']:.0f}, {_db(r['vs_exact']['psnr'])} dB" for r in res) + ". "
        text += ("Its time gain is in what scales with Gaussians (interpolation, the C4GS bytes), not the exact decode, "
                 "which computes every Gaussian anyway; the analysis costs about "
                 f"{mean_of(pruned, 'analysis_ms_per_clip'):.0f} ms a clip at 64 px (see the stream table).")
        out.append(text)
    ctx = [by[n] for n in ("T=2", "T=3", "T=6") if n in by]
    if ctx:
        out.append("**Context frames** change the model's input, so everything moves: " + "; ".join(
            f"{r['name']} {r['ms_per_frame']:.2f} ms, loss {loss_db(r, base):+.2f} dB, {_db(r['vs_exact']['psnr'])} dB from exact"
            for r in ctx) + f" (T=4: {t0:.2f} ms). The decoder attends over T × 64 + 512 tokens, so fewer frames decode faster "
            "and more slower; T=6 here is stride 1, outside training.")
    res = [by[n] for n in ("128 px", "256 px") if n in by]
    if res:
        out.append("**Resolution** is render cost: " + "; ".join(
            f"{r['name']} renders in {r['render_ms_per_frame']:.2f} ms a frame ({1 - r['decode_share']:.0%} of its time)" for r in res)
            + f", against {base['render_ms_per_frame']:.2f} ms at 64 px. Against the 64 px ground truth, supersampling "
            "changes " + ", ".join(f"{r['gt']['psnr'] - base['gt']['psnr']:+.2f} dB" for r in res) + ".")
    prec = [by[n] for n in ("f16 package", "int8 package") if n in by]
    if prec:
        text = "**Package precision**: " + "; ".join(
            f"{r['name']} decodes in {r['decode_ms_per_frame']:.2f} ms a set (f32 {base['decode_ms_per_frame']:.2f}), "
            f"{_db(r['vs_exact']['psnr'])} dB from exact, loss {loss_db(r, base):+.2f} dB" for r in prec) + ". "
        degenerate = [r for r in rows if r["precision"] == "int8" and r["keyframes"]["mode"] == "adaptive"
                      and r["exact_decodes_per_clip"] >= 64]
        if degenerate:
            text += ("Adaptive keyframes do not combine with int8: " + ", ".join(r["name"] for r in degenerate)
                     + " decodes every one of the 64 targets. The int8 package quantises activations dynamically, with "
                     "each run's own range, so a time's positions depend on the batch it is decoded in and jitter from one "
                     "time to the next by more than these tolerances: no check passes. Uniform keyframes do not check, "
                     "and combine with it.")
        out.append(text)
    if "f16 wire" in by:
        r = by["f16 wire"]
        out.append(f"**f16 wire** halves the bytes ({r['bytes_per_frame_f32']:,.0f} → {r['bytes_per_frame_f16']:,.0f} a frame) "
                   f"at {_db(r['vs_exact']['psnr'])} dB from exact: the cheapest knob there is.")
    rises = [(r["name"], r["peak_rise_mib"] or 0.0) for r in rows]
    exact_rise = max(0.0, base["peak_rise_mib"] or 0.0)
    small = [n for n, v in rises if v < 10]
    out.append(f"**Memory**: the peak rises about {exact_rise:.0f} MiB over the resident set while exact decodes its 64 sets "
               f"(batches of 16); {len(small)} of {len(rows)} settings stay within 10 MiB of where they started. The "
               "process holds the three engines and the harness's reference renders throughout, so its absolute peak "
               "(the table) grows with the resolution of those references.")
    return out


def mean_of(rows: list[dict], key: str) -> float:
    values = [r[key] for r in rows if r.get(key) is not None]
    return sum(values) / len(values) if values else 0.0


def document(results: dict, png_name: str) -> str:
    rows = results["settings"]
    base = baseline(rows)
    fronts = {"vs exact": pareto(rows, vs_exact), "vs ground truth": pareto(rows, gt_psnr)}
    presets = choose_presets(rows)
    m = results["machine"]
    load = results.get("load_average", {})
    L = []
    add = L.append
    add("# Speed against accuracy: the measured trade")
    add("")
    add("What each of the service's speed knobs costs in accuracy on the default model, c4g-tiny "
        f"({results['gaussians']} Gaussians a set), on its {len(results['clips'])} committed test clips "
        f"({', '.join(results['clips'])}). Generated by `python -m c4g.bench.tradeoffs_report` from the results of "
        "`cargo bench -p c4g-engine --bench tradeoffs` (`engine/benches/tradeoffs.rs`): do not edit by hand, "
        "remake it (below).")
    add("")
    add(f"**Machine:** {m['cpu']}, {m['threads']} threads, {m['memory_gib']} GiB, {m['os']}; no GPU "
        f"({m['execution']}); ONNX Runtime `{m['onnxruntime']}`. Wall time of the whole sweep "
        f"{results['elapsed_s'] / 60:.1f} min; load average (1, 5, 15 min) {load.get('start', '?')} at the start "
        f"and {load.get('end', '?')} at the end: the machine is shared, so times are per clip the best of "
        f"{results['rounds']} rounds (each round times every setting once, in its own shuffled order; at least 3, more while a 9-minute "
        "budget allows), and ratios "
        "between rows are firmer than the absolute numbers (`ms_per_frame_rounds` in the JSON has every round).")
    if results.get("quick"):
        add("")
        add("**Quick mode** (`C4G_TRADEOFFS_QUICK=1`): a smoke subset on one clip, one run each. Not the numbers to quote.")
    for note in results.get("notes", []):
        add("")
        add(f"**Note:** {note}")
    add("")
    add("## The knobs")
    add("| knob | values swept | what it is |")
    add("|---|---|---|")
    add("| keyframes | exact; every 0.1, 0.2, 0.3 s (1, 2, 3 source frames); count 2, 4, 8, 16; adaptive tolerance 0.02, 0.01, 0.005, 0.002 scene units | `Keyframes` (`engine/src/keyframes.rs`): decode exact sets at keyframes and interpolate per Gaussian between them; adaptive places keyframes until position checks at requested times pass the tolerance |")
    add("| pruning | off; contribution floor 0.5 px (the `PruneOptions` default) and 2 px; opacity floor 1/255 | `SceneAnalysis` + `GaussianSet::select` (`analysis/src/pruning.rs`): drop Gaussians that contribute less than the floor to every analysed render |")
    add("| context frames | 2, 3, 4 (baseline), 6 | how many of each clip's 7 frames (0–0.6 s, 10 fps) the encoder sees, spread evenly with both ends: "
        "T=2: frames 0 6; 3: 0 3 6; 4: 0 2 4 6 (the clips' own, stride 2 as in training); 6: 0 1 2 4 5 6. "
        "The model was trained with 3–4 frames at stride 2: T=2 (stride 6), T=3 (stride 3) and T=6 (stride 1) are all outside it, T=6 most. At T=3 and T=6 some ground-truth targets are context frames |")
    add("| render resolution | 64 (baseline), 128, 256 px | the CPU rasterizer's output size, C4G's intrinsics scaled; scored against the 64 px ground truth after box-downsampling, against exact at its own size |")
    add("| package precision | f32 (baseline), f16, int8 | `python -m c4g.package.precision` conversions of the package, made into a temporary directory when the sweep starts |")
    add("| wire precision | f32 (baseline), f16 | the C4GS payload (`formats/src/c4gs.rs`): the sets are packed and unpacked before they are rendered, so f16's rounding is in the quality |")
    add("")
    add("The sweep is not the cross product: every knob is varied alone from the baseline `exact` (f32 package, 4 context "
        "frames, exact decodes, no pruning, 64 px, f32 wire), then a few combinations that look like presets, at 64 px and "
        "at 128 and 256 px and with the int8 package.")
    add("")
    add("## How a setting is measured")
    add(f"- **Output:** per clip {results['output_frames']} times evenly over the context span (0–0.6 s), the three nearest the "
        "ground-truth targets (0.1, 0.3, 0.5 s) moved onto them; each rendered from the clip's camera at that time (poses "
        "interpolated between the clip's frames).")
    add("- **Time per output frame:** wall time of producing the sets (decode, or keyframe decodes and interpolation; "
        "then `select` when pruning: keyframes are pruned before they are interpolated) plus rendering them on the CPU "
        "rasterizer, divided by the frames; per clip the best of the rounds, summed over clips. *Decode share* is the producing "
        "part. Not in it, and given in the JSON: the encode (once per clip), the C4GS round trip, and the pruning analysis.")
    add(f"- **Pruning analysis** (once per clip, like an encode): exact sets at {results['analysis']['times']} times evenly over "
        f"the span, rendered at the setting's resolution from {results['analysis']['views']}. The clips' novel camera "
        "(moved (0.15, −0.05, 0.1) and turned 6°) is not among them: its scores say whether pruning holds away from the "
        "analysed views.")
    add("- **Sets per second:** the producing part alone (no render), 64 sets per clip: the rate a stream of sets could "
        "reach before the network.")
    add("- **Bytes per frame:** one set's C4GS frame (8-byte time + 14 values a Gaussian) at f32 and f16, after pruning.")
    add("- **Peak memory:** the process's peak resident set (`VmHWM`, reset by writing 5 to `/proc/self/clear_refs` before "
        "each setting): it includes every loaded engine and the harness's own buffers (the exact renders kept for "
        "comparison), so read differences; *rise* is the peak minus the resident set at the setting's start.")
    add("- **Against ground truth:** PSNR and SSIM (`c4g_renderer::fidelity`) at the three targets from the clip's camera "
        "(*interpolated*) and from the novel camera, renders clamped to [0, 1], as `engine/tests/tiny_quality.rs` scores "
        "them; mean over images. *Loss* = the baseline's ground-truth PSNR (mean of both) minus the setting's.")
    add("- **Against exact:** the same renders against the baseline's at the same resolution: PSNR of the squared error "
        "pooled over all 64 path frames and the novel views (*identical* when it is zero), the worst frame's PSNR, and SSIM "
        "over every 4th path frame and the novel views.")
    add("")
    add("## Presets")
    pool = f"{PRESET_POOL['resolution']} px, {PRESET_POOL['context_frames']} context frames and {PRESET_POOL['precision']} package"
    add(f"Chosen by rule among the request options (keyframes, pruning, wire) at the baseline's {pool}; count "
        "keyframes are not candidates, since a count means coarser keyframes on every longer clip. Each rule takes the "
        "fastest candidate within a loss bound against ground truth *and* a fidelity bound against the exact renders: "
        "c4g-tiny's own error (about 21 dB against ground truth) hides what keyframes, pruning and f16 add, so the loss "
        "alone would call nearly every setting equal. The fidelity bounds are in 8-bit terms: 48.1 dB = 20·log₁₀ 255 is "
        "an RMS difference of one level, 40 dB one of 1 % of the range. Times within "
        f"{TIME_TIE:.0%} of the fastest candidate's count as a tie (run-to-run noise here is larger), which goes to the "
        "one closer to exact. A preset so chosen is never dominated among the candidates (no candidate is as fast and "
        "as good against both ground truth and exact); the plot rings it.")
    add("")
    add("| preset | rule | setting | ms / frame | sets/s | bytes / frame | loss dB | vs exact PSNR (worst frame) |")
    add("|---|---|---|---|---|---|---|---|")
    adaptive_only = choose_presets(rows, modes=("exact", "adaptive"))

    def preset_row(label, rule, r):
        if r is None:
            return f"| {label} | {rule.why} | no setting meets it | | | | | |"
        wire_bytes = r["bytes_per_frame_f16"] if r["wire"] == "f16" else r["bytes_per_frame_f32"]
        return (f"| {label} | {rule.why} | {_describe(r)} | {r['ms_per_frame']:.2f} | {r['sets_per_s']:,.0f} | "
                f"{wire_bytes:,.0f} ({r['wire']}, {r['gaussians']:.0f} Gaussians) | {loss_db(r, base):+.2f} | "
                f"{_db(r['vs_exact']['psnr'])} ({_db(r['vs_exact']['psnr_worst_frame'])}) |")

    for rule in PRESET_RULES:
        add(preset_row(f"**{rule.name}**", rule, presets.get(rule.name)))
        alternative = adaptive_only.get(rule.name)
        if rule.max_loss_db is not None and alternative is not presets.get(rule.name):
            add(preset_row(f"{rule.name}, adaptive only", rule, alternative))
    add("")
    verdicts = served_verdicts(rows, presets)
    if verdicts:
        parts = []
        for name, v in verdicts.items():
            r, pick = v["row"], presets.get(name)
            same = pick is not None and pick["name"] == r["name"]
            if same:
                verdict = "the rule's pick on this run"
            elif v["within_bounds"] and v["within_tie"]:
                verdict = (f"not the rule's pick on this run ({pick['name']}) but within its bounds and its time tie "
                           f"({r['ms_per_frame']:.2f} against {pick['ms_per_frame']:.2f} ms a frame, {_db(r['vs_exact']['psnr'])} dB against "
                           f"{_db(pick['vs_exact']['psnr'])} dB from exact), so it stays")
            else:
                verdict = (f"**{'outside its rule' if not v['within_bounds'] else 'slower than the time tie'} on this run** "
                           f"({r['ms_per_frame']:.2f} ms a frame, loss {loss_db(r, base):+.2f} dB, {_db(r['vs_exact']['psnr'])} dB from exact; "
                           f"the rule picks {pick['name'] if pick else 'nothing'}): `service/src/sets/quality.rs` should follow")
            parts.append(f"`{name}` serves {r['name']}: {verdict}")
        add("**What the service serves** (`service/src/sets/quality.rs`, set from an earlier run; the wire precision is the "
            "request's `precision`): " + "; ".join(parts) + ".")
        add("")
    add("**Seconds are this clip's.** A spacing in seconds (`every_s`) means something different on every clip: here "
        "the context frames are 0.2 s apart, so every 0.2 s puts a keyframe on each context frame, where the model's "
        "motion turns its corners (`engine/src/keyframes.rs`), and 0.3 s is 1.5 context spacings. On a clip whose "
        "context frames are seconds apart the same `every_s` would decode more than ten keyframes per interval. So a preset "
        "that uses `every_s` should be set as a multiple of the clip's context spacing (the service knows it), or "
        "replaced by its *adaptive only* line: the tolerance is in scene units, which C4G's normalisation (first to "
        "last context camera = 1, or median depth 2) makes comparable across clips, and adaptive keyframes always "
        "include the context times. What adaptive costs here is its checks: at least the ends, the two inner context "
        "times and two checks per interval, 10 or more exact decodes for 64 frames, where uniform keyframes take 3 or 4.")
    add("")
    add(f"![PSNR against the exact output (left) and against ground truth (right) for every setting, against time per output frame on a log axis; the Pareto front as a staircase with its settings labelled, presets ringed]({png_name})")
    add("")
    add("## The stream rate")
    add(f"The issue's acceptance: at the `fast` preset the stream delivers ≥ {STREAM_TARGET_SETS_PER_S:,.0f} sets a second at "
        "≤ 0.5 dB against exact. Producing rates (no render, no network; 64 sets over a 0.6 s clip, so keyframe decodes are "
        "spread over few frames: a longer stream amortises them further), fastest first. The pruning analysis is once per "
        "clip (like the encode, which no row counts): *frames to amortise it* is how long a stream over one clip must be "
        f"before the analysis still leaves {STREAM_TARGET_SETS_PER_S:,.0f} sets a second.")
    add("")
    fast = presets.get("fast")
    if fast is not None:
        n = frames_to_amortise(fast)
        verdict = "meets" if fast["sets_per_s"] >= STREAM_TARGET_SETS_PER_S else "does not meet"
        text = (f"**At the proposed `fast` preset** ({fast['name']}) the sets are produced at {fast['sets_per_s']:,.0f} a second "
                f"with a loss of {loss_db(fast, base):+.2f} dB: it {verdict} the target on this run")
        if fast.get("analysis_ms_per_clip") and n is not None:
            text += f", once a stream over a clip is {n:,} frames or longer (to amortise the pruning analysis)"
        add(text + ". Against the exact rate of this run, " f"{base['sets_per_s']:,.0f} sets a second, that is "
            f"{fast['sets_per_s'] / base['sets_per_s']:.0f} times as many.")
        add("")
    add("| setting | sets/s | exact decodes per clip | pruning analysis, ms per clip | frames to amortise it | loss dB | vs exact PSNR | ≥ 1,000 sets/s |")
    add("|---|---|---|---|---|---|---|---|")
    for r in sorted(rows, key=lambda r: -r["sets_per_s"]):
        ok = r["sets_per_s"] >= STREAM_TARGET_SETS_PER_S
        n = frames_to_amortise(r)
        analysis = r.get("analysis_ms_per_clip")
        add(f"| {r['name']} | {r['sets_per_s']:,.0f} | {r['exact_decodes_per_clip']:g} | "
            f"{'—' if analysis is None else f'{analysis:.0f}'} | {'—' if analysis is None else ('never' if n is None else f'{n:,}')} | "
            f"{loss_db(r, base):+.2f} | {_db(r['vs_exact']['psnr'])} | {'yes' if ok else ''} |")
    add("")
    add("## Every setting")
    add("Front marks: on the Pareto front of time against PSNR vs exact, or vs ground truth.")
    add("")
    L.extend(table(rows, fronts, presets))
    add("")
    add("## What the numbers say")
    L.extend(f"- {f}" for f in findings(rows))
    add("")
    add("## How to read it")
    add("- **Left panel, against exact:** what a setting changes in what the client sees, at its own resolution. Above "
        "about 40 dB the renders differ by under 1 % of the range; a point on the dotted line is identical to exact.")
    add("- **Right panel, against ground truth:** the model's accuracy, which the knobs can only lose (or, by chance, gain "
        "a little). c4g-tiny's own error (about 21 dB) dwarfs what keyframes, pruning and f16 wire add, so most of the "
        "sweep lies within a few hundredths of a dB of exact there; context frames and precision move the model itself.")
    add("- **The front** is what to choose from: a setting off it is beaten on both axes by one on it. Higher "
        "resolutions and int8 have their own points; the presets are limited to request options (above).")
    add("- Numbers are c4g-tiny's (512 Gaussians, a 64-token-per-frame encoder) on 0.6 s synthetic clips: the official "
        "model decodes far slower (see `benchmarks.md`), which makes keyframes worth more, and a longer clip spreads "
        "each keyframe over more frames.")
    add("")
    add("## Not measured here")
    add("- **The refiner** (steps, sampler, guidance): its only package here, the test fixture "
        "`models/fixtures/wan-vace-tiny`, has random weights, so there is no accuracy to measure: not against ground "
        "truth, and not against its own most-steps output either (a random network's velocity field is no denoiser, so "
        "more steps do not converge on a better image and the PSNR between step counts says nothing about the real "
        "model's). Its cost is already measured by `cargo bench -p c4g-refiner --bench refine` (steps 1, 2, 4, 8 at "
        "guidance 1 and 5; `benchmarks.md`), and the sampler does not change it: UniPC and Euler both run the "
        "transformer once per step (`refiner/src/pipeline.rs`; twice with guidance ≠ 1), so time is linear in steps "
        "times guidance runs plus the fixed control input and decode. The trade needs trained Wan-VACE weights.")
    add("- **A GPU**: this sweep runs where the service's tests run, on CPUs; the GPU's table is the section *On a GPU* below (`scripts/device-check`, through the PyTorch mirror).")
    add("- **The network**: sets per second are produced sets; the gRPC stream adds serialisation (the C4GS round trip "
        "is in the JSON as `wire_ms_per_frame`) and transport.")
    add("")
    add("## Remake it")
    add("```sh")
    add("source scripts/env.sh                       # PYTHON (for the f16 / int8 conversions), ORT_DYLIB_PATH")
    add("cargo bench -p c4g-engine --bench tradeoffs  # writes target/tradeoffs.json (C4G_TRADEOFFS_OUT overrides)")
    add("$PYTHON -m c4g.bench.tradeoffs_report --results target/tradeoffs.json --out docs")
    add("```")
    add("`C4G_TRADEOFFS_QUICK=1` runs a smoke subset (one clip, four settings) in seconds.")
    add("")
    return "\n".join(L)


# Sections other benches write into the page (`engine/benches/query_dropping.rs`,
# `engine/benches/official_keyframes.rs`, `c4g.bench.gpu_tradeoffs` on a GPU), between a begin and an end marker: kept verbatim, after
# the sweep's own text, whenever the page is remade.
KEPT_BEGIN = "<!-- kept: begin {name} -->"
KEPT_END = "<!-- kept: end {name} -->"
KEPT_SECTIONS = ("query-dropping", "official-keyframes", "gpu", "fit")


def kept_sections(previous: str) -> str:
    """The marked sections of the page as it was (markers included), in `KEPT_SECTIONS` order."""
    kept = []
    for name in KEPT_SECTIONS:
        begin, end = KEPT_BEGIN.format(name=name), KEPT_END.format(name=name)
        if begin in previous and end in previous.split(begin, 1)[1]:
            body = previous.split(begin, 1)[1].split(end, 1)[0]
            kept.append(f"{begin}{body}{end}\n")
    return "\n".join(kept)


def with_section(page: str, name: str, body: str) -> str:
    """`page` with the marked section `name` replaced by `body` (appended when it has none)."""
    begin, end = KEPT_BEGIN.format(name=name), KEPT_END.format(name=name)
    block = f"{begin}\n{body.strip()}\n{end}\n"
    if begin in page and end in page.split(begin, 1)[1]:
        before, rest = page.split(begin, 1)
        return before + block + rest.split(end, 1)[1].lstrip("\n")
    return page.rstrip("\n") + "\n\n" + block


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.bench.tradeoffs_report", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", type=Path, default=Path("target/tradeoffs.json"), help="the harness's JSON")
    ap.add_argument("--out", type=Path, default=Path("docs"), help="folder for tradeoffs.md and tradeoffs.png")
    ap.add_argument(
        "--section",
        metavar="NAME=FILE",
        help=f"only put FILE (Markdown another bench wrote) into the page as its kept section NAME ({', '.join(KEPT_SECTIONS)})",
    )
    args = ap.parse_args(argv)
    if args.section:
        name, _, source = args.section.partition("=")
        if name not in KEPT_SECTIONS or not source:
            ap.error(f"--section takes NAME=FILE with NAME one of {', '.join(KEPT_SECTIONS)}")
        page = args.out / "tradeoffs.md"
        page.write_text(with_section(page.read_text(), name, Path(source).read_text()))
        print(f"wrote section {name} of {page}")
        return 0
    results = json.loads(args.results.read_text())
    rows = results["settings"]
    args.out.mkdir(parents=True, exist_ok=True)
    fronts = {"vs exact": pareto(rows, vs_exact), "vs ground truth": pareto(rows, gt_psnr)}
    presets = choose_presets(rows)
    png = args.out / "tradeoffs.png"
    plot(rows, fronts, presets, png)
    page = args.out / "tradeoffs.md"
    kept = kept_sections(page.read_text()) if page.exists() else ""
    page.write_text(document(results, png.name) + ("\n" + kept if kept else ""))
    for name, r in presets.items():
        print(f"{name}: {r['name']} ({r['ms_per_frame']:.2f} ms/frame, {r['sets_per_s']:,.0f} sets/s, loss {loss_db(r, baseline(rows)):+.2f} dB)")
    print(f"wrote {args.out / 'tradeoffs.md'} and {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
