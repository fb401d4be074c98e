"""c4g's Python tooling: the PyTorch mirror of C4G and everything made from it or held against it.

Subpackages, roughly in the order a model goes through them:
- `model`: the PyTorch mirror (official parameter names): sizes, layers, encoder, decoder and its
  forms, checkpoint loading, random initialisation, the time policy, frame preprocessing.
- `package`: model packages (model.json + ONNX graphs): the export tool, precision conversions,
  upgrades of a package in place, a package back to a checkpoint, the committed test fixtures.
- `raster`: the 3DGS forward model: the float64 reference, the fast and the dense differentiable
  rasterizers, the rasterizer fixture scenes, PSNR and SSIM in float64.
- `train`: the procedural training scenes, their rendered splits, feature-lifting targets and the
  training loop of c4g-tiny.
- `eval`: scoring models and the service: the evaluation-only world, the paper's protocols against
  a running server, TAP-Vid tracks and metrics, generalisation, segmentation, real footage.
- `bench`: measurements and the reports made from them (docs/benchmarks.md, docs/tradeoffs.md,
  docs/time-policy.md).
- `formats`: independent readers of the service's 4D exports (`.ply.zip`, `.splatv`).
- `wan`: the video-diffusion refiner's side: Wan2.1-VACE export, LoRA, reference outputs.

Commands are modules: `python -m c4g.package.export --help`.
"""
