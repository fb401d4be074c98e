"""Readers of the service's 4D exports written apart from the service, so that each checks the other
(tests/e2e/exports.rs runs them).

- `frames_zip`: a `.ply.zip` (one 3DGS `.ply` per time) with `zipfile` and `plyfile`.
- `splatv`: a `.splatv` (splaTV's web player), from the format's specification.
"""
