"""The refiner's measurements (docs/benchmarks.md, "Refiner").

- `startup`: the worker's start-up time and memory, with and without a merged LoRA.
- `external_initializers`: what ONNX Runtime holds for weights given as external initializers.
- `layouts`: C4G's refinement layout against VACE's: tokens and time per denoising step.
"""
