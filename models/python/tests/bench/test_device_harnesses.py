"""The GPU harnesses scripts/device-check runs, checked where there is no GPU: they run on the CPU
at a small size and count work that could be wrong, and they say so when CUDA is missing."""

from __future__ import annotations

import json

import onnxruntime as ort
import pytest

from c4g.bench import gpu as bench_gpu, ort_parity


def test_bench_gpu_counts_the_work_of_each_call_and_its_share_of_the_peak(tmp_path):
    out = tmp_path / "rows.json"
    code = bench_gpu.main(
        ["--device", "cpu", "--config", "official-small", "--dtype", "fp32", "bf16", "--frames", "2", "--batch", "1", "2", "--repeats", "1", "--json", str(out)]
    )
    assert code == 0
    runs = json.loads(out.read_text())["runs"]
    assert [r["dtype"] for r in runs] == ["fp32", "bf16"]
    # The work does not depend on the dtype (the same calls, counted the same way).
    assert [r["tflop"] for r in runs[0]["rows"]] == [r["tflop"] for r in runs[1]["rows"]]
    rows = runs[0]["rows"]
    assert [(r["call"], r["frames"], r["batch"]) for r in rows] == [("encode", 2, 0), ("decode", 2, 1), ("decode", 2, 2)]
    # Two targets are twice the decoder's work of one (every layer runs per target).
    assert rows[2]["tflop"] == pytest.approx(2 * rows[1]["tflop"], rel=1e-6)
    assert all(r["tflop"] > 0 and 0 < r["of_measured_peak"] for r in rows)
    assert all(r["of_spec_peak"] is None for r in rows), "no data-sheet peak for a CPU"


def test_bench_gpu_refuses_cuda_where_there_is_none():
    if bench_gpu.torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    assert bench_gpu.main(["--config", "official-small"]) == 2


def test_ort_parity_says_when_onnxruntime_has_no_cuda(capsys):
    if "CUDAExecutionProvider" in ort.get_available_providers():
        pytest.skip("this onnxruntime has CUDA")
    assert ort_parity.main(["models/fixtures/c4g-small"]) == 2
    assert "no CUDA provider" in capsys.readouterr().out
