"""The 4D feature field through the client against the real server (c4g-tiny lifts its encoder's
features, width 128): decodes with features agree bit for bit across JSON, ``C4GS`` version 2
(the renderer's writer, read by this package's reader) and gRPC ``Decode``; feature renders;
segments; and the server's refusals as the client's error types with the server's message,
on c4g-tiny and on ``models/c4g-tiny-objects`` (whose object-id features this server cannot
lift)."""

from __future__ import annotations

import asyncio
import json
import struct
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest

import c4g_client as c4g
from c4g_client import AsyncClient, Client
from c4g_client._sets import from_json
from conftest import REPO, start_server

FIELDS = ("means", "quats", "scales", "opacities", "colors")
WIDTH = 128
TIMES = [0.0, 0.25, 0.6]


def assert_same_sets(a, b) -> None:
    assert [s.time for s in a] == [s.time for s in b]
    for x, y in zip(a, b):
        for name in (*FIELDS, "features"):
            assert getattr(x, name).tobytes() == getattr(y, name).tobytes(), name


def test_the_model_reports_its_feature_width(client: Client):
    (model,) = client.models()
    assert model.feature_lifting == WIDTH


def test_features_over_json_and_binary_are_the_same_floats(client: Client, clip: c4g.Clip):
    binary = client.decode(clip.id, TIMES, features=True)
    payload = client.gaussians_raw(clip.id, TIMES, format="binary", features=True)
    # The server's own writer made version 2, with F after the header.
    assert payload[4:6] == struct.pack("<H", 2) and struct.unpack_from("<I", payload, 16) == (WIDTH,)
    as_json = from_json(json.loads(client.gaussians_raw(clip.id, TIMES, features=True)))
    assert_same_sets(binary, as_json)
    for s in binary:
        assert s.features.shape == (512, WIDTH) and s.features.dtype == np.float32
        assert np.isfinite(s.features).all() and np.abs(s.features).max() > 0
    # The Gaussians are those of a decode without features, which has none.
    plain = client.decode(clip.id, TIMES)
    for with_f, without in zip(binary, plain):
        assert without.features is None
        for name in FIELDS:
            assert getattr(with_f, name).tobytes() == getattr(without, name).tobytes()
    one = client.decode(clip.id, 0.25, features=True)
    assert one.features.tobytes() == binary[1].features.tobytes()


def test_f16_features_are_the_f32_features_rounded_to_half(client: Client, clip: c4g.Clip):
    exact = client.decode(clip.id, [0.1], features=True)[0]
    half = client.decode(clip.id, [0.1], features=True, precision="f16")[0]
    rounded = np.clip(exact.features, -65504, 65504).astype(np.float16).astype(np.float32)
    np.testing.assert_array_equal(half.features, rounded)


def test_features_travel_with_taken_stacked_and_torch_sets(client: Client, clip: c4g.Clip):
    sets = client.decode(clip.id, TIMES, features=True)
    visible = sets[0].take(sets[0].opacities > 0.5)
    assert visible.features.shape == (len(visible), WIDTH)
    np.testing.assert_array_equal(visible.features, sets[0].features[sets[0].opacities > 0.5])
    assert c4g.stack(sets)["features"].shape == (3, 512, WIDTH)
    torch = pytest.importorskip("torch")
    tensors = sets[0].to_torch()
    assert tensors.features.dtype == torch.float32 and tensors.features.shape == (512, WIDTH)
    np.testing.assert_array_equal(tensors.features.numpy(), sets[0].features)


def test_grpc_decodes_with_features_are_the_rest_decodes(client: Client, clip: c4g.Clip):
    pytest.importorskip("grpc")
    over_grpc = client.grpc_decode(clip.id, TIMES, features=True)
    assert_same_sets(over_grpc, client.decode(clip.id, TIMES, features=True))
    assert_same_sets(
        client.grpc_decode(clip.id, TIMES, features=True, precision="f16"),
        client.decode(clip.id, TIMES, features=True, precision="f16"),
    )
    # Twenty sets with features are 5.8 MB in one message, past grpcio's default 4 MiB limit.
    many = [float(t) for t in np.linspace(0.0, 0.6, 20)]
    assert_same_sets(
        client.grpc_decode(clip.id, many, features=True), client.decode(clip.id, many, features=True)
    )
    plain = client.grpc_decode(clip.id, 0.25)
    assert isinstance(plain, c4g.GaussianSet) and plain.features is None
    assert plain.means.tobytes() == client.decode(clip.id, 0.25).means.tobytes()


def test_a_features_render_is_h_w_f_floats_and_pca_an_rgb_image(client: Client, clip: c4g.Clip):
    image = client.render(clip.id, 0.2, width=40, height=24, format="features")
    assert isinstance(image, c4g.FeatureImage) and image.time == 0.2
    assert image.array.shape == (24, 40, WIDTH) and image.array.dtype == np.float32
    assert np.isfinite(image.array).all() and np.abs(image.array).max() > 0
    # Composited like colour, with no background: the mean feature a pixel shows is the
    # render divided by its alpha, and every Gaussian's feature is within the set's range.
    alpha = client.render(clip.id, 0.2, width=40, height=24, format="alpha").array
    mean = image.array / alpha[:, :, None]
    features = client.decode(clip.id, 0.2, features=True).features
    assert (mean.max(axis=(0, 1)) <= features.max(axis=0) + 1e-4).all()
    assert (mean.min(axis=(0, 1)) >= features.min(axis=0) - 1e-4).all()
    pca = client.render(clip.id, 0.2, width=40, height=24, format="features_pca")
    assert isinstance(pca, c4g.Image) and pca.array.shape == (24, 40, 3)
    # The clip's PCA basis is fixed: the same request gives the same colours.
    assert client.render(clip.id, 0.2, width=40, height=24, format="features_pca").png == pca.png


def test_a_click_segments_gaussians_whose_masks_cover_the_clicked_pixel(client: Client, clip: c4g.Clip):
    x, y = 20, 12
    times = [0.0, 0.2, 0.4]
    segment = client.segment(clip.id, click=(0.2, x + 0.5, y + 0.5), times=times, width=40, height=24)
    assert (segment.width, segment.height, segment.t, segment.threshold) == (40, 24, 0.2, pytest.approx(0.8))
    assert segment.feature.shape == (WIDTH,) and 0 < len(segment.gaussians) < 512
    assert [m.t for m in segment.masks] == times
    for mask in segment.masks:
        assert mask.array.shape == (24, 40) and mask.array.dtype == bool
        assert int(mask.array.sum()) == mask.area
    assert segment.masks[1].array[y, x]
    # The selection is the rule the docs state: the Gaussians whose feature at t has a cosine
    # similarity of at least the threshold with the click's feature.
    features = client.decode(clip.id, 0.2, features=True).features.astype(np.float64)
    norms = np.linalg.norm(features, axis=1) * np.linalg.norm(segment.feature)
    cosine = features @ segment.feature / norms
    selected = np.zeros(512, dtype=bool)
    selected[segment.gaussians] = True
    clear = np.abs(cosine - 0.8) > 1e-4  # rounding decides the ties, not the rule
    assert (selected[clear] == (cosine[clear] >= 0.8)).all()
    # Selecting by that feature at that time selects the same Gaussians, with the same masks.
    again = client.segment(clip.id, feature=segment.feature, t=0.2, times=times, width=40, height=24)
    assert again.gaussians.tolist() == segment.gaussians.tolist()
    assert [m.counts for m in again.masks] == [m.counts for m in segment.masks]
    assert len(client.segment(clip.id, feature=segment.feature, t=0.2, threshold=0.99).gaussians) <= len(
        segment.gaussians
    )


def test_the_async_client_decodes_features_and_segments_the_same(server: str, client: Client, clip: c4g.Clip):
    async def body(c: AsyncClient):
        sets = await c.decode(clip.id, TIMES, features=True)
        image = await c.render(clip.id, 0.2, width=16, height=16, format="features")
        segment = await c.segment(clip.id, click={"t": 0.2, "x": 8.5, "y": 8.5}, width=16, height=16)
        over_grpc = await c.grpc_decode(clip.id, TIMES, features=True)
        return sets, image, segment, over_grpc

    async def main():
        async with AsyncClient(server) as c:
            return await body(c)

    sets, image, segment, over_grpc = asyncio.run(main())
    assert_same_sets(sets, client.decode(clip.id, TIMES, features=True))
    assert_same_sets(over_grpc, sets)
    np.testing.assert_array_equal(
        image.array, client.render(clip.id, 0.2, width=16, height=16, format="features").array
    )
    blocking = client.segment(clip.id, click=(0.2, 8.5, 8.5), width=16, height=16)
    assert segment.gaussians.tolist() == blocking.gaussians.tolist()


def test_what_the_server_refuses_raises_the_clients_error_with_its_message(client: Client, clip: c4g.Clip):
    with pytest.raises(c4g.InvalidInput) as e:
        client.gaussians_raw(clip.id, 0.2, format="splat", features=True)
    assert e.value.status == 400 and ".splat format has no room for features" in e.value.message
    with pytest.raises(c4g.Unsupported) as e:
        client.decode(clip.id, 0.2, features=True, prune=c4g.Prune(drop_queries=True))
    assert e.value.status == 422 and "drop_queries" in e.value.message
    pytest.importorskip("grpc")
    with pytest.raises(c4g.Unsupported) as e:
        client.grpc_decode(clip.id, 0.2, features=True, prune=c4g.Prune(drop_queries=True))
    assert e.value.grpc_code == "INVALID_ARGUMENT" and e.value.kind == "unsupported"
    assert "drop_queries" in e.value.message
    with pytest.raises(c4g.InvalidInput, match="not both"):
        client.segment(clip.id, click=(0.2, 1.5, 1.5), feature=np.ones(WIDTH))
    with pytest.raises(c4g.InvalidInput) as e:
        client.segment(clip.id, feature=np.ones(7))
    assert "the feature has 7 values; the model's lifted features have 128" in e.value.message
    with pytest.raises(c4g.InvalidInput, match="not all zeros"):
        client.segment(clip.id, feature=np.zeros(WIDTH))


@pytest.fixture(scope="module")
def objects_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A server of ``models/c4g-tiny-objects``, whose feature decoder lifts object ids."""
    proc, url = start_server(
        tmp_path_factory.mktemp("objects"), {"C4G_MODEL": str(REPO / "models" / "c4g-tiny-objects")}
    )
    try:
        yield url
    finally:
        proc.stop()


def test_an_object_id_package_refuses_every_feature_request(objects_server: str, frames: list[Path]):
    with Client(objects_server) as c:
        assert c.models()[0].feature_lifting == 8
        clip = c.upload(frames, fps=10)
        calls = [
            lambda: c.decode(clip.id, 0.2, features=True),
            lambda: c.render(clip.id, 0.2, format="features"),
            lambda: c.render(clip.id, 0.2, format="features_pca"),
            lambda: c.segment(clip.id, click=(0.2, 3.5, 3.5)),
        ]
        for call in calls:
            with pytest.raises(c4g.Unsupported) as e:
                call()
            assert e.value.status == 422 and "object-id" in e.value.message
        # Sets without features still decode.
        assert c.decode(clip.id, 0.2).features is None
