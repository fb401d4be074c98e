"""Training feature lifting: the object-id render beside the synthetic clips, the maps and targets of
each kind, features rendered like colours, and a short training run of each kind that ends in a
package declaring what it lifts."""

import json

import numpy as np
import pytest
import torch

from c4g.model.network import C4G
from c4g.package import export
from c4g.train import lifting
from c4g.train.dataset import Split, generate, window
from c4g.train.loop import TINY, initialise, main, predict
from c4g.train.synthetic import OBJECT_IDS, make_scene, render_clip, render_object_ids


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("data")
    generate("train", 2, out, processes=1, object_ids=True)
    generate("validation", 1, out, processes=1, object_ids=True)
    return out


@pytest.mark.parametrize("world", [1, 2])
def test_object_ids_mark_the_moving_objects_where_the_dynamic_mask_does(world):
    scene = make_scene(5, world=world)
    times = np.arange(11) / 10
    ids = render_object_ids(scene, times, 64)
    clip = render_clip(scene, times, 64)
    assert ids.shape == (11, 64, 64) and ids.dtype == np.uint8
    assert set(np.unique(ids)) == set(range(len(scene.objects) + 1))  # the room and every object seen
    # Both come from the same Gaussians' weights: they disagree only on a few boundary pixels.
    assert ((ids > 0) == clip.dynamic_mask).mean() > 0.99


def test_a_split_without_object_ids_is_as_it_was(tmp_path, data):
    plain = Split.load(generate("train", 2, tmp_path, processes=1))
    with_ids = Split.load(data / "train.npz")
    assert plain.object_ids is None and with_ids.object_ids.shape == with_ids.dynamic.shape
    for key in ("frames", "depth", "dynamic", "world_to_camera", "times", "seeds"):
        np.testing.assert_array_equal(getattr(plain, key), getattr(with_ids, key), err_msg=key)


def test_object_id_maps_are_patch_fractions_and_targets_one_hot(data):
    sample = window(Split.load(data / "train.npz"), 0, 0, 3)
    model = C4G(TINY)
    maps = lifting.context_maps(model, sample, torch.zeros(3, TINY.tokens_per_frame, TINY.feature_width), "object-id")
    assert maps.shape == (3, TINY.tokens_per_frame, OBJECT_IDS)
    torch.testing.assert_close(maps.sum(-1), torch.ones(3, TINY.tokens_per_frame))
    # Patch (0, 0) of the first context frame: the fraction of its 8 x 8 pixels of each id.
    ids = sample.object_ids[sample.context[0], :8, :8]
    np.testing.assert_allclose(maps[0, 0].numpy(), np.bincount(ids.ravel(), minlength=OBJECT_IDS) / 64)
    target = lifting.targets(model, sample, sample.targets, "object-id")
    assert target.shape == (len(sample.targets), 64, 64, OBJECT_IDS)
    assert torch.equal(target.argmax(-1), torch.from_numpy(sample.object_ids[sample.targets]).long())
    assert torch.equal(target.sum(-1), torch.ones(target.shape[:-1]))


def test_features_render_like_colours(data):
    """Rendering each Gaussian's colour as its feature with the dense rasterizer gives the fast
    rasterizer's colour image (the same forward model; float32 sums in another order)."""
    sample = window(Split.load(data / "train.npz"), 0, 0, 3)
    model = C4G(TINY)
    initialise(model, 0)
    with torch.no_grad():
        out, gaussians = predict(model, sample, sample.targets)
        size = TINY.image_size
        f = 0.8767 * size
        poses = torch.from_numpy(sample.world_to_camera[sample.targets]).float()
        rendered = lifting.render_features(gaussians, gaussians[4], (f, f, size / 2, size / 2), poses, size)
    assert out["rgb"].abs().max() > 0.1
    torch.testing.assert_close(rendered, out["rgb"], atol=1e-4, rtol=0)


def test_the_encoder_kind_compares_patch_means_with_the_target_frames_features(data):
    sample = window(Split.load(data / "train.npz"), 0, 0, 3)
    model = C4G(TINY)
    initialise(model, 0)
    target = lifting.targets(model, sample, sample.targets, "encoder")
    assert target.shape == (len(sample.targets), TINY.tokens_per_frame, TINY.feature_width)
    # An image that is each patch's target feature, constant over the patch, has zero loss.
    grid, patch = TINY.grid, TINY.patch
    image = target.reshape(-1, grid, grid, TINY.feature_width).repeat_interleave(patch, 1).repeat_interleave(patch, 2)
    assert float(lifting.loss(model, image, target, "encoder")) < 1e-6
    assert float(lifting.loss(model, image + 0.5, target, "encoder")) == pytest.approx(0.5, abs=1e-5)


@pytest.mark.parametrize("kind", ["object-id", "encoder"])
def test_a_short_lifting_run_trains_the_stream_and_its_package_declares_the_kind(tmp_path, data, kind):
    run = tmp_path / "run"
    args = ["--data", str(data), "--run", str(run), "--steps", "2", "--batch", "1", "--context-frames", "2", "--threads", "1",
            "--validate-every", "1000", "--features", kind, "--feature-weight", "0.5"]  # fmt: skip
    assert main(args) == 0
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["feature"]) and r["feature"] > 0 for r in log)
    recipe = json.loads((run / "recipe.json").read_text())
    width = OBJECT_IDS if kind == "object-id" else TINY.feature_width
    assert (recipe["features"], recipe["feature_weight"], recipe["config"]["feature_dim"]) == (kind, 0.5, width)
    state = torch.load(run / "c4g-tiny.ckpt")["state_dict"]
    assert state["encoder.gmae_decoder.y_norm.weight"].shape == (width,)
    # Training moved the stream away from its initialisation: the y norm starts at exactly 1.
    assert not torch.equal(state["encoder.gmae_decoder.y_norm.weight"], torch.ones(width))
    out = tmp_path / "pkg"
    rc = export.main(["--checkpoint", str(run / "c4g-tiny.ckpt"), "--config", str(run / "config.json"), "--recipe", str(run / "recipe.json"),
                      "--decoder-form", "plain", "--out", str(out)])  # fmt: skip
    assert rc == 0
    manifest = json.loads((out / "model.json").read_text())
    assert manifest["feature_decoder"] == {"feature_width": width, "kind": kind}
    assert "feature_decoder" not in manifest["provenance"]  # trained, not random


def test_object_id_lifting_refuses_a_split_without_ids(tmp_path):
    data = tmp_path / "data"
    generate("train", 1, data, processes=1)
    generate("validation", 1, data, processes=1)
    args = ["--data", str(data), "--run", str(tmp_path / "run"), "--steps", "1", "--batch", "1", "--context-frames", "2", "--features", "object-id"]
    assert main(args) == 2


def test_a_feature_stream_alone_trains_on_a_model_it_starts_from(tmp_path, data):
    """The object-id stage of c4g-tiny v2: --feature-stream-only moves the feature stream alone, and a
    checkpoint whose feature stream has another width (another kind) gives everything else."""
    start_run = tmp_path / "start"
    common = ["--data", str(data), "--steps", "2", "--batch", "1", "--context-frames", "2", "--threads", "1", "--validate-every", "1000"]
    assert main([*common, "--run", str(start_run), "--features", "encoder"]) == 0
    run = tmp_path / "objects"
    args = [*common, "--run", str(run), "--features", "object-id", "--feature-stream-only", "--init-from", str(start_run / "c4g-tiny.ckpt")]
    assert main(args) == 0
    start = torch.load(start_run / "c4g-tiny.ckpt")["state_dict"]
    after = torch.load(run / "c4g-tiny.ckpt")["state_dict"]
    from c4g.model.network import is_feature_stream

    moved = [k for k in after if is_feature_stream(k[len("encoder."):])]
    assert moved and after["encoder.gmae_decoder.y_norm.weight"].shape == (OBJECT_IDS,)
    for k, v in after.items():
        if not is_feature_stream(k[len("encoder."):]):
            torch.testing.assert_close(v, start[k], rtol=0, atol=1e-6, msg=k)
    assert not torch.equal(after["encoder.gmae_decoder.y_norm.weight"], torch.ones(OBJECT_IDS))
    assert main([*common, "--run", str(tmp_path / "bad"), "--features", "object-id", "--feature-stream-only"]) == 2


def test_segmentation_iou_is_the_objects_mean_and_leaves_the_stage_out():
    from c4g.eval.segmentation import iou

    truth = np.zeros((4, 4), np.uint8)
    truth[:2, :2] = 1
    predicted = truth.copy()
    assert iou(predicted, truth) == 1.0
    predicted[0, 0] = 0  # object 1: 3 of 4 pixels
    predicted[3, 3] = 2  # object 2: in the prediction only
    assert iou(predicted, truth) == pytest.approx((3 / 4 + 0.0) / 2)
    assert iou(np.zeros((4, 4), np.uint8), np.zeros((4, 4), np.uint8)) is None


def test_the_object_id_loss_prefers_the_right_small_object_to_the_majority():
    """L1 against one-hot ids rewards 'stage everywhere'; the balanced cross-entropy does not."""
    model = C4G(TINY)
    ids = torch.zeros(1, 8, 8, dtype=torch.long)
    ids[0, :2, :2] = 1  # a small object: 4 of 64 pixels
    target = torch.nn.functional.one_hot(ids, OBJECT_IDS).float()
    stage_everywhere = torch.nn.functional.one_hot(torch.zeros_like(ids), OBJECT_IDS).float() * 4
    right = target * 4
    assert float(lifting.loss(model, right, target, "object-id")) < float(lifting.loss(model, stage_everywhere, target, "object-id"))
