"""Training plumbing: the head gain folds into the official checkpoint layout without changing the
model's output, and a run stopped and resumed ends exactly where an uninterrupted run does."""

import numpy as np
import torch

from c4g.model.checkpoint import load_checkpoint
from c4g.model.network import C4G
from c4g.train.dataset import generate
from c4g.train.loop import TINY, attach_gain, initialise, main, official_state_dict


def test_the_folded_checkpoint_decodes_like_the_training_model(tmp_path):
    model = C4G(TINY)
    initialise(model, seed=3)
    attach_gain(model)
    path = tmp_path / "tiny.ckpt"
    torch.save({"state_dict": official_state_dict(model)}, path)
    plain = load_checkpoint(path, TINY)
    frames = torch.rand(3, 3, 64, 64) * 2 - 1
    ctx, tgt = torch.tensor([[0.0, 0.5, 1.0]] * 2), torch.tensor([0.25, 0.75])
    with torch.no_grad():
        a = model.decode_canonical(model.encode(frames), ctx, tgt)
        b = plain.decode_canonical(plain.encode(frames), ctx, tgt)
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    scales = a[..., 3:6]
    assert 0.01 < scales.median() < 0.5, "the initial Gaussians are neither points nor the whole scene"


def test_a_stopped_and_resumed_run_ends_where_an_uninterrupted_one_does(tmp_path):
    data = tmp_path / "data"
    generate("train", 3, data, processes=1)
    generate("validation", 1, data, processes=1)
    common = ["--data", str(data), "--steps", "3", "--batch", "1", "--context-frames", "2", "--threads", "1", "--validate-every", "1000"]
    assert main([*common, "--run", str(tmp_path / "whole")]) == 0
    assert main([*common, "--run", str(tmp_path / "split"), "--stop-after", "2"]) == 0
    assert not (tmp_path / "split/c4g-tiny.ckpt").exists()
    assert main([*common, "--run", str(tmp_path / "split")]) == 0
    whole = torch.load(tmp_path / "whole/c4g-tiny.ckpt")["state_dict"]
    split = torch.load(tmp_path / "split/c4g-tiny.ckpt")["state_dict"]
    for k in whole:
        np.testing.assert_allclose(split[k].numpy(), whole[k].numpy(), rtol=1e-5, atol=1e-6, err_msg=k)
    # A time budget stops after the step that runs past it (here the first), as resumable as a step count.
    assert main([*common, "--run", str(tmp_path / "timed"), "--time-budget", "0"]) == 0
    assert torch.load(tmp_path / "timed/last.pt", weights_only=False)["step"] == 1
    assert main([*common, "--run", str(tmp_path / "timed")]) == 0
    timed = torch.load(tmp_path / "timed/c4g-tiny.ckpt")["state_dict"]
    for k in whole:
        np.testing.assert_allclose(timed[k].numpy(), whole[k].numpy(), rtol=1e-5, atol=1e-6, err_msg=k)
    # A different recipe in the same folder is refused rather than silently mixed.
    assert main([*common[:-4], "--lr", "1e-3", "--run", str(tmp_path / "split")]) == 2


def test_a_step_off_the_cpu_renders_through_the_dense_rasterizer_to_the_same_loss(tmp_path, monkeypatch):
    """Off the CPU (a GPU run: `--device cuda`) the renders are `c4g.raster.dense`'s, since the Numba
    kernels run on the CPU only. No GPU here: the CPU stands in for the device, with the dense
    rasterizer put where the tiled one is chosen. One step each way from the same start: the loss
    terms, made before any update, and the gradient's norm agree to float rounding (the two
    rasterizers sum in different orders; their backward passes are held to each other in
    tests/raster/test_fast.py)."""
    import json

    import c4g.raster.dense
    import c4g.train.loop

    data = tmp_path / "data"
    generate("train", 2, data, processes=1)
    generate("validation", 1, data, processes=1)
    common = ["--data", str(data), "--steps", "1", "--batch", "2", "--context-frames", "3", "--threads", "1", "--validate-every", "1000"]
    assert main([*common, "--run", str(tmp_path / "tiled")]) == 0
    monkeypatch.setattr(c4g.train.loop, "fast", c4g.raster.dense)
    assert main([*common, "--run", str(tmp_path / "dense")]) == 0
    tiled, dense = (json.loads((tmp_path / run / "log.jsonl").read_text().splitlines()[0]) for run in ("tiled", "dense"))
    for key in ("mse", "ssim", "depth", "alpha", "chamfer", "colour", "grad_norm"):
        assert abs(dense[key] - tiled[key]) <= 1e-4 * abs(tiled[key]) + 1e-7, (key, tiled[key], dense[key])


def test_windows_at_wider_strides_put_targets_between_their_context_frames(tmp_path):
    from c4g.train.dataset import Split, random_windows, span, window

    split = Split.load(generate("validation", 1, tmp_path, processes=1, world=2, frames=17))
    assert split.frames.shape[1] == 17
    s = window(split, 0, 2, 4, stride=4)
    np.testing.assert_array_equal(s.context, [0, 4, 8, 12])
    np.testing.assert_array_equal(s.targets, [1, 2, 3, 5, 6, 7, 9, 10, 11])
    np.testing.assert_allclose(s.times[s.context], np.array([2, 6, 10, 14]) / 10)
    # The model's frame: the first context camera is the identity whatever the stride.
    np.testing.assert_allclose(s.world_to_camera[0], np.eye(4), atol=1e-12)
    assert span(8, 2) == 15 and span(5, 4) == 17
    rng = np.random.default_rng(0)
    assert all(len(w.times) == 17 for w in random_windows(split, rng, 3, 5, 4))
    try:
        random_windows(split, rng, 1, 6, 4)
    except ValueError as e:
        assert "21 frames" in str(e)
    else:
        raise AssertionError("a window longer than the clips was cut")


def test_a_run_over_strides_and_context_sizes_records_its_recipe_and_policy(tmp_path):
    import json

    data = tmp_path / "data"
    generate("train", 2, data, processes=1, world=2, frames=13)
    generate("validation", 1, data, processes=1, world=2, frames=13)
    common = ["--data", str(data), "--steps", "2", "--batch", "1", "--threads", "1", "--validate-every", "1000"]
    run = tmp_path / "run"
    args = [*common, "--context-frames", "2,3,4", "--strides", "2,4", "--time-policy", "frame-step", "--run", str(run)]
    assert main(args) == 0
    recipe = json.loads((run / "recipe.json").read_text())
    assert (recipe["strides"], recipe["time_policy"], recipe["context_frames"]) == ("2,4", "frame-step", "2,3,4")
    steps = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert all(s["stride"] in (2, 4) and s["T"] in (2, 3, 4) for s in steps)
    # Eight context frames at stride 4 span 29 frames: no clip of 13 holds them.
    assert main([*common, "--context-frames", "8", "--strides", "4", "--run", str(tmp_path / "bad")]) == 2


def test_a_run_from_a_checkpoint_starts_from_its_weights_and_caps_its_targets(tmp_path):
    """`--init-from` (c4g-tiny v2 starts from v1): before any step the training model decodes as the
    checkpoint does, the head gain taken back out; `--targets-per-window` renders at most that many
    targets a window. With lr 0 the run ends on the checkpoint's weights exactly."""
    import json

    data = tmp_path / "data"
    generate("train", 2, data, processes=1, world=2, frames=13)
    generate("validation", 1, data, processes=1, world=2, frames=13)
    start = tmp_path / "start.ckpt"
    model = C4G(TINY)
    initialise(model, seed=5)
    attach_gain(model)
    torch.save({"state_dict": official_state_dict(model)}, start)
    run = tmp_path / "run"
    args = ["--data", str(data), "--steps", "2", "--batch", "1", "--threads", "1", "--validate-every", "1000", "--lr", "0",
            "--context-frames", "3", "--strides", "4", "--targets-per-window", "2", "--init-from", str(start), "--run", str(run)]
    assert main(args) == 0
    before = torch.load(start)["state_dict"]
    after = torch.load(run / "c4g-tiny.ckpt")["state_dict"]
    for k in before:
        torch.testing.assert_close(after[k], before[k], rtol=1e-6, atol=1e-7, msg=k)
    recipe = json.loads((run / "recipe.json").read_text())
    assert recipe["targets_per_window"] == 2 and len(recipe["init_from_sha256"]) == 64


def test_a_cuda_device_that_is_not_there_is_refused_before_any_work(tmp_path, capsys):
    import pytest

    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    assert main(["--data", str(tmp_path / "none"), "--run", str(tmp_path / "run"), "--device", "cuda"]) == 2
    assert "sees no CUDA device" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_the_log_depth_term_costs_a_relative_error_the_same_at_every_distance():
    """`--depth-loss log`: a render 20 % too near costs as much at 2 baselines as at 50 (a slow
    camera's scene), where the inverse-depth term gives the far scene almost nothing."""
    from types import SimpleNamespace

    from c4g.train.loop import loss_terms

    def depth_term(truth: float, kind: str) -> float:
        size = 32  # at least the 1024 surface points the Chamfer terms draw
        sample = SimpleNamespace(
            frames=np.zeros((1, size, size, 3), np.float32),
            dynamic=np.zeros((1, size, size), bool),
            depth=np.full((1, size, size), truth, np.float32),
            world_to_camera=np.eye(4)[None],
        )
        out = {"rgb": torch.zeros(1, size, size, 3), "alpha": torch.ones(1, size, size), "expected_depth": torch.full((1, size, size), 0.8 * truth)}
        gaussians = (torch.zeros(1, 4, 3), None, None, None, torch.zeros(1, 4, 3))
        return float(loss_terms(out, gaussians, sample, np.array([0]), 0.0, np.random.default_rng(0), kind)["depth"])

    np.testing.assert_allclose([depth_term(2.0, "log"), depth_term(50.0, "log")], -np.log(0.8), rtol=1e-5)
    assert depth_term(50.0, "inverse") < depth_term(2.0, "inverse") / 20
