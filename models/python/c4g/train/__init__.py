"""Training small C4G models (c4g-tiny) on procedural scenes.

- `synthetic`: procedural dynamic scenes with ground truth (worlds 1 and 2).
- `dataset`: rendered splits of those scenes and the training samples cut from them.
- `lifting`: what feature lifting trains on (2D feature maps, their targets, the rendered features).
- `loop`: the training loop, its recipe and losses (`python -m c4g.train.loop`).
"""
