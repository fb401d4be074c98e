"""The Python side of the video-diffusion refiner: Wan2.1-VACE, built from diffusers' own classes.

- `configs`: the real 1.3B configuration and the tiny random-weight stand-in (same structure, CPU-sized).
- `onnx_graphs`: the transformer and VAE encoder / decoder as ONNX graphs (parameter names kept, fused
  attention, fixed shapes).
- `lora`: LoRA files in PEFT and original-Wan naming, the module-name map between them, and the merge at
  export (`merge_into_transformer`: `export --lora`, before `--fp16` rounds the weights).
- `reference`: diffusers' WanVACEPipeline runs and schedules that the Rust refiner must reproduce.
- `export`: the command line (`python -m c4g.wan.export`) and the refiner package format (refiner.json).
- `check_merged`: a package with its LoRA merged at export against diffusers' f32 module with it merged.
- `c4g_layout`: C4G's own refinement layout (the one its published LoRA was trained with), in PyTorch.
- `text`: the text side: umT5's encoder and tokenizer, as the pipeline turns a caption into an embedding.
- `bench`: the worker's start-up memory, how ONNX Runtime holds external weights, and C4G's layout
  against VACE's (docs/benchmarks.md).
"""
