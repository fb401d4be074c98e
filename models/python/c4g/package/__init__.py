"""Model packages (docs/package.md: model.json + ONNX graphs): made, converted and read back.

- `export`: checkpoint (official layout) → package (`python -m c4g.package.export`).
- `precision`: an f32 package converted to f16 or int8.
- `query_subset_upgrade`: an existing package's decoder given the `query_indices` input, from the
  package alone.
- `to_checkpoint`: a package's weights back in the official checkpoint layout (the export run
  backwards).
- `fixture`: the committed test packages (models/fixtures/) and their reference outputs.
"""
