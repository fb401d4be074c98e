"""Scoring models and the service, with their fixtures and readers.

- `world`: a second procedural world, used only to evaluate (never trained on).
- `fixtures`: the evaluation fixtures (models/fixtures/eval/) from the procedural worlds.
- `tapvid`: TAP-Vid style point-track files and the TAP-Vid metrics.
- `lk_baseline`: the 2D tracking baseline (OpenCV's pyramidal Lucas-Kanade).
- `protocols`: the paper's protocols (point tracking, novel views) against a running service
  (`scripts/eval`).
- `cameras`: recovered cameras against known ones, through a running service.
- `held_out`: a trained checkpoint on the held-out test split against simple baselines; writes the
  service's test clips.
- `generalisation`: a package on two worlds, its training generator's and one it never saw.
- `segmentation`: lifted object ids scored as segmentation IoU on the same two worlds.
- `real_footage`: a package on real footage: pictures and numbers for a model card.
"""
