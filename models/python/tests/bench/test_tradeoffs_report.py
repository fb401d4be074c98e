"""The trade-off report's selection logic (c4g.bench.tradeoffs_report): the Pareto front and the presets, on a
small synthetic results list whose answers are known by construction."""

import json
import math

import pytest

from c4g.bench.tradeoffs_report import Rule, choose_presets, document, pareto, served_verdicts, vs_exact, gt_psnr, main


def row(name, ms, gt, exact, *, mode="adaptive", resolution=64, context=4, precision="f32", knob="keyframes"):
    return {
        "name": name,
        "knob": knob,
        "keyframes": {"mode": mode, "tolerance": 0.01, "seconds": 0.2, "n": 8},
        "prune": None,
        "context_frames": context,
        "resolution": resolution,
        "precision": precision,
        "wire": "f32",
        "ms_per_frame": ms,
        "decode_ms_per_frame": ms * 0.9,
        "render_ms_per_frame": ms * 0.1,
        "decode_share": 0.9,
        "sets_per_s": 1000.0 / ms,
        "sets_per_s_with_analysis": 900.0 / ms,
        "exact_decodes_per_clip": 8,
        "gaussians": 512,
        "bytes_per_frame_f32": 28680,
        "bytes_per_frame_f16": 14344,
        "peak_rss_mib": 150.0,
        "peak_rise_mib": 1.0,
        "gt": {"psnr": gt, "psnr_interpolated": gt, "psnr_novel": gt, "ssim": 0.6},
        "vs_exact": {"psnr": exact, "psnr_worst_frame": exact, "ssim": 1.0},
    }


def rows():
    return [
        row("exact", 40.0, 21.00, None, mode="exact", knob="baseline"),
        row("fine", 10.0, 20.98, 55.0),          # 0.02 dB loss
        row("medium", 5.0, 20.85, 45.0),         # 0.15 dB loss
        row("coarse", 2.0, 20.60, 42.0),         # 0.40 dB loss
        row("coarse twin", 2.05, 20.70, 44.0),   # 0.30 dB loss, within 5 % of coarse's time and closer to exact
        row("far", 1.8, 20.95, 35.0),            # 0.05 dB loss but 35 dB from exact: fails both fidelity bounds
        row("worse and slower", 12.0, 20.50, 30.0),  # dominated by fine on both axes
        row("tied but slower", 10.5, 20.98, 55.0),   # as good as fine, slower: dominated
        row("count", 1.0, 20.99, 50.0, mode="count"),              # fastest, but not a preset candidate
        row("int8", 1.5, 20.70, 35.0, precision="int8", knob="precision"),  # outside the preset pool
        row("too lossy", 0.5, 19.0, 20.0),       # 2 dB loss
    ]


def names(front):
    return [r["name"] for r in front]


def test_identical_renders_count_as_the_best_quality_against_exact():
    assert vs_exact(rows()[0]) == math.inf
    assert vs_exact(rows()[1]) == 55.0


def test_front_against_exact_holds_exactly_the_undominated_rows_fastest_first():
    # fine is slower than count but closer to exact, so it stays.
    front = names(pareto(rows(), vs_exact))
    assert front == ["too lossy", "count", "fine", "exact"]


def test_front_against_ground_truth_drops_dominated_and_tied_slower_rows():
    front = names(pareto(rows(), gt_psnr))
    assert "worse and slower" not in front
    assert "tied but slower" not in front
    assert front == ["too lossy", "count", "exact"]


def test_front_without_the_dominating_rows():
    pool = [r for r in rows() if r["name"] not in ("count", "too lossy", "int8")]
    assert names(pareto(pool, gt_psnr)) == ["far", "fine", "exact"]
    # Against both qualities, rows that trade one for the other are all undominated.
    assert names(pareto(pool, gt_psnr, vs_exact)) == ["far", "coarse", "coarse twin", "medium", "fine", "exact"]


def test_presets_are_the_fastest_candidates_within_their_bounds():
    presets = choose_presets(rows(), tie=0.0)
    assert presets["exact"]["name"] == "exact"
    # fine (0.02 dB, 55 dB from exact) meets 0.1 dB and 48.1 dB; medium loses 0.15 dB; far is
    # 35 dB from exact.
    assert presets["balanced"]["name"] == "fine"
    # coarse loses 0.40 dB at 42 dB from exact; count is faster and better but a count, int8 is
    # outside the pool, "too lossy" loses 2 dB, far fails 40 dB.
    assert presets["fast"]["name"] == "coarse"


def test_a_near_tie_in_time_goes_to_the_setting_closer_to_exact():
    assert choose_presets(rows())["fast"]["name"] == "coarse twin"
    assert choose_presets(rows(), tie=0.01)["fast"]["name"] == "coarse"


def test_served_presets_are_checked_against_their_rules():
    presets = choose_presets(rows())
    verdicts = served_verdicts(rows(), presets, served={"balanced": "fine", "fast": "far"})
    # fine is balanced's pick; far is fast enough but 35 dB from exact, outside fast's 40 dB.
    assert verdicts["balanced"]["within_bounds"] and verdicts["balanced"]["within_tie"]
    assert not verdicts["fast"]["within_bounds"] and verdicts["fast"]["within_tie"]
    # coarse meets fast's bounds and is within the tie of its pick (coarse twin); medium is slower.
    coarse = served_verdicts(rows(), presets, served={"fast": "coarse"})["fast"]
    assert coarse["within_bounds"] and coarse["within_tie"]
    medium = served_verdicts(rows(), presets, served={"fast": "medium"})["fast"]
    assert medium["within_bounds"] and not medium["within_tie"]
    # A served setting the sweep did not measure is left out.
    assert served_verdicts(rows(), presets, served={"fast": "unmeasured"}) == {}


def test_a_fidelity_bound_excludes_rows_far_from_exact():
    assert choose_presets(rows(), (Rule("loss only", 0.5),))["loss only"]["name"] == "far"
    assert choose_presets(rows(), (Rule("strict", 0.5, 44.5),))["strict"]["name"] == "medium"


def test_a_rule_no_row_meets_is_left_out_and_a_missing_baseline_is_an_error():
    assert "impossible" not in choose_presets(rows(), (Rule("impossible", -1.0),))
    with pytest.raises(ValueError):
        choose_presets(rows()[1:])


def test_presets_lie_on_the_candidates_front():
    results = rows()
    pool = [r for r in results if r["keyframes"]["mode"] != "count" and r["precision"] == "f32"]
    front = pareto(pool, gt_psnr, vs_exact)
    for r in choose_presets(results).values():
        assert any(f is r for f in front), r["name"]


def test_the_report_writes_the_document_and_plot(tmp_path):
    results = {
        "quick": True,
        "gaussians": 512,
        "clips": ["seed-1"],
        "output_frames": 64,
        "rounds": 1,
        "elapsed_s": 12.0,
        "analysis": {"times": 5, "views": "the context cameras"},
        "machine": {"cpu": "AMD EPYC", "threads": 2, "memory_gib": 24, "os": "Debian", "execution": "CPU", "onnxruntime": "1.31.1"},
        "load_average": {"start": "0.1", "end": "0.2"},
        "notes": [],
        "settings": rows(),
    }
    path = tmp_path / "results.json"
    path.write_text(json.dumps(results))
    assert main(["--results", str(path), "--out", str(tmp_path / "docs")]) == 0
    text = (tmp_path / "docs/tradeoffs.md").read_text()
    assert "| **fast** |" in text and "(tradeoffs.png)" in text
    assert (tmp_path / "docs/tradeoffs.png").stat().st_size > 10_000
    assert text == document(results, "tradeoffs.png")

    # Another bench's section goes in between its markers, and survives the page being remade.
    section = tmp_path / "dropping.md"
    section.write_text("## Dropping queries\n\n| a | b |\n")
    assert main(["--section", f"query-dropping={section}", "--out", str(tmp_path / "docs")]) == 0
    assert main(["--results", str(path), "--out", str(tmp_path / "docs")]) == 0
    remade = (tmp_path / "docs/tradeoffs.md").read_text()
    assert remade.startswith(document(results, "tradeoffs.png"))
    assert "<!-- kept: begin query-dropping -->\n## Dropping queries\n\n| a | b |\n<!-- kept: end query-dropping -->" in remade
    section.write_text("## Dropping queries, again\n")
    assert main(["--section", f"query-dropping={section}", "--out", str(tmp_path / "docs")]) == 0
    again = (tmp_path / "docs/tradeoffs.md").read_text()
    assert again.count("kept: begin query-dropping") == 1 and "again" in again and "| a | b |" not in again


def test_frames_to_amortise_the_pruning_analysis():
    from c4g.bench.tradeoffs_report import frames_to_amortise

    r = row("pruned", 1.0, 21.0, 50.0)
    r["sets_per_s"] = 2000.0
    r["analysis_ms_per_clip"] = 100.0
    # n / (n / 2000 + 0.1) >= 1000  <=>  n >= 0.1 / (1/1000 - 1/2000) = 200.
    assert frames_to_amortise(r) == 200
    r["analysis_ms_per_clip"] = None
    assert frames_to_amortise(r) == 0
    r["sets_per_s"] = 900.0
    assert frames_to_amortise(r) is None
