"""The PyTorch mirror of C4G, with the official checkpoint's parameter names.

Modules, in the order data flows through them:
- `config`: every size of the network (official, the reduced reference size, and our own).
- `preprocess`: the reference's frame preprocessing, with Pillow.
- `attention`: scaled dot-product attention, exportable as ONNX Runtime's fused MultiHeadAttention.
- `layers`: attention with QK-norm and 2D RoPE, MLPs, LayerScale, transformer blocks.
- `aggregator`: the VGGT aggregator with its DINOv2 patch embedding (the encoder).
- `decoder`: time embedding, the Gaussian decoder, the Gaussian head, the feature-lifting decoder.
- `precomputed`: the decoder's precomputed form (the context features' first projection once per clip).
- `query_subset`: the decoder run on a subset of its queries.
- `network`: `C4G`, the whole model.
- `time_policy`: the normalisation of timestamps (the reference, frame-step and stable policies);
  `python -m c4g.model.time_policy --write-cases` writes the engine's cross-check table.
- `checkpoint`: loading a checkpoint in the official layout with strict key matching.
- `init`: random weights that make every part of the network matter (test models, cost at scale).
"""
