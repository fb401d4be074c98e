"""Training plumbing: the head gain folds into the official checkpoint layout without changing the
model's output, and a run stopped and resumed ends exactly where an uninterrupted run does."""

import numpy as np
import torch

from c4g.checkpoint import load_checkpoint
from c4g.dataset import generate
from c4g.model import C4G
from c4g.train import TINY, attach_gain, initialise, main, official_state_dict


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
    # A different recipe in the same folder is refused rather than silently mixed.
    assert main([*common[:-4], "--lr", "1e-3", "--run", str(tmp_path / "split")]) == 2
