"""The PyTorch mirror of C4G: the architecture, checkpoint loading, the time policy and the export tool.

Modules, in the order data flows through them:
- `config`: every size of the network (official, the reduced reference size, and our own).
- `attention`: scaled dot-product attention, exportable as ONNX Runtime's fused MultiHeadAttention.
- `layers`: attention with QK-norm and 2D RoPE, MLPs, LayerScale, transformer blocks.
- `aggregator`: the VGGT aggregator with its DINOv2 patch embedding (the encoder).
- `decoder`: time embedding, the Gaussian decoder, the Gaussian head, the feature-lifting decoder.
- `model`: `C4G`, the whole model with the official parameter names.
- `time_policy`: the normalisation of timestamps (the reference, frame-step and stable policies).
- `time_policy_plot`: the deviation plot of docs/time-policy.md (the package's graphs on ONNX Runtime).
- `checkpoint`: loading a checkpoint in the official layout with strict key matching.
- `init`: random weights that make every part of the network matter (test models, cost at scale).
- `export`: checkpoint → model package (model.json + ONNX graphs).
- `preprocess`: the reference's frame preprocessing, with Pillow.
- `fixture`: builds the committed test package and its reference outputs.

Rendering and images (the references the renderer crate is held to, and training's renderer):
- `raster_reference`: the 3DGS forward model in float64 NumPy.
- `raster_scenes`: the rasterizer fixture scenes.
- `render_torch`: the same forward model, differentiable, in PyTorch.
- `metrics_reference`: PSNR and SSIM in float64.

The service's 4D exports, read back by readers that are not the service's (tests/e2e/exports.rs):
- `frames_zip`: a `.ply.zip` with `zipfile` and `plyfile`.
- `splatv`: a `.splatv`, written from the format's specification (splaTV's viewer).
"""
