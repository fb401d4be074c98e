"""The 3D Gaussian splatting forward model in Python: the references the renderer crate is held to,
and the rasterizers that make data and train.

- `reference`: the forward model in float64 NumPy, written for clarity (the renderer's reference).
- `fast`: a fast differentiable rasterizer (Numba, tiled) for data, training and evaluation on a CPU.
- `dense`: the same forward model, differentiable, dense in PyTorch (every Gaussian at every pixel;
  any device).
- `grad_reference`: float64 autograd gradients of the forward model (both footprints), the reference the
  renderer crate's backward pass is held to (models/fixtures/gradients/).
- `scenes`: the rasterizer fixture scenes (models/fixtures/scenes/) with the reference's renders.
- `metrics`: PSNR and SSIM in float64, and the fixture that pins the renderer's.
"""
