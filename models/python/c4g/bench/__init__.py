"""Measurements, studies and the documents made from them (docs/benchmarks.md, docs/tradeoffs.md,
docs/time-policy.md). Each prints or writes what it measured and where.

- `decoder`: the exact decoder's speed, ONNX Runtime against PyTorch eager.
- `precision`: what a package's f16 and int8 conversions cost and save against f32.
- `capacity`: what c4g-tiny's size costs: the candidates' inference and training time.
- `keyframe_placement`: where keyframe interpolation goes wrong and what other placements gain.
- `gpu`: the model's cost on a GPU through the PyTorch mirror.
- `gpu_tradeoffs`: the speed/accuracy trade on a GPU through the mirror.
- `ort_parity`: a package on ONNX Runtime's CUDA provider against its CPU provider.
- `tradeoffs_report`: docs/tradeoffs.md and its plot, from the Rust trade-off harness's results.
- `time_policy_plot`: the deviation plot of docs/time-policy.md (a package's graphs on ONNX Runtime).
"""
