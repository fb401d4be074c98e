"""The PyTorch mirror of C4G: the architecture, checkpoint loading, the time policy and the export tool.

Modules, in the order data flows through them:
- `config`: every size of the network (official, the reduced reference size, and our own).
- `layers`: attention with QK-norm and 2D RoPE, MLPs, LayerScale, transformer blocks.
- `aggregator`: the VGGT aggregator with its DINOv2 patch embedding (the encoder).
- `decoder`: time embedding, the Gaussian decoder, the Gaussian head, the feature-lifting decoder.
- `model`: `C4G`, the whole model with the official parameter names.
- `time_policy`: the normalisation of timestamps (reference behaviour and the stable default).
- `checkpoint`: loading a checkpoint in the official layout with strict key matching.
- `export`: checkpoint → model package (model.json + ONNX graphs).
"""
