"""dfd.encoders and dfd.dinov2: per-pixel unit features; DINOv2 loads the official key names."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dfd.dinov2 import ENV_CHECKPOINT, DinoV2Encoder, DinoVisionTransformer, load_dinov2
from dfd.encoders import Encoder, FilterBankEncoder, encode_views, get_encoder
from dfd.errors import DfdInputError, MissingCheckpointError
from dfd.render import render_views
from dfd.shapes import ellipsoids


@pytest.fixture(scope="module")
def views():
    V, F = ellipsoids([((0, 0, 0), (0.6, 1.0, 0.5)), ((0.9, 0.3, 0), (0.35, 0.2, 0.2))], subdivisions=2)
    return render_views(V, F, n_views=6, resolution=56)


def test_filterbank_views_unit_features(views):
    enc = get_encoder("filterbank")
    assert isinstance(enc, Encoder)
    X = encode_views(enc, views)
    assert X.shape == views.rgb.shape[:3] + (enc.feature_dim,) and X.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(X[views.mask], axis=1), 1.0, atol=1e-5)
    assert (X[~views.mask] == 0).all()
    # the geometry channels (normals, depth) are used: encode() of colours alone differs
    Y = enc.encode(views.rgb)
    assert Y.shape == X.shape
    assert np.abs(X - Y)[views.mask].max() > 0.1
    np.testing.assert_allclose(Y[..., -4:], 0.0)


def test_filterbank_mirror_invariant(views):
    """Mirroring an image mirrors its features (no handedness): symmetry detection relies on it."""
    enc = FilterBankEncoder()
    X = enc.encode(views.rgb)
    Xm = enc.encode(views.rgb[:, :, ::-1].copy())
    np.testing.assert_allclose(Xm[:, :, ::-1], X, atol=1e-4)


def test_filterbank_rejects_bad_shape():
    with pytest.raises(DfdInputError, match=r"\(B, H, W, 3\)"):
        FilterBankEncoder().encode(np.zeros((4, 4, 3)))


def _tiny_vit():
    torch.manual_seed(0)
    model = DinoVisionTransformer(img_size=56, patch_size=14, embed_dim=64, depth=2, num_heads=2)
    with torch.no_grad():
        for block in model.blocks:  # LayerScale starts at 1e-5: make the blocks matter
            block.ls1.gamma.fill_(0.5)
            block.ls2.gamma.fill_(0.5)
    return model


def test_vit_has_official_key_names():
    keys = set(_tiny_vit().state_dict())
    for k in [
        "patch_embed.proj.weight", "patch_embed.proj.bias", "cls_token", "pos_embed", "mask_token",
        "blocks.0.norm1.weight", "blocks.0.attn.qkv.weight", "blocks.0.attn.qkv.bias", "blocks.0.attn.proj.weight",
        "blocks.0.ls1.gamma", "blocks.0.norm2.bias", "blocks.0.mlp.fc1.weight", "blocks.0.mlp.fc2.bias",
        "blocks.0.ls2.gamma", "blocks.1.ls2.gamma", "norm.weight", "norm.bias",
    ]:
        assert k in keys, k


def test_dinov2_checkpoint_round_trip(tmp_path, views):
    model = _tiny_vit()
    path = tmp_path / "tiny_dinov2.pth"
    torch.save(model.state_dict(), path)
    loaded = load_dinov2(path, num_heads=2)
    assert loaded.embed_dim == 64 and len(loaded.blocks) == 2 and loaded.patch_size == 14
    x = torch.randn(2, 3, 84, 70)  # not the 56 px training size: position embeddings interpolate
    with torch.no_grad():
        np.testing.assert_allclose(loaded.forward_patch_tokens(x), model.eval().forward_patch_tokens(x), atol=1e-5)

    enc = get_encoder("dinov2", checkpoint=path, num_heads=2)
    assert enc.feature_dim == 64
    X = encode_views(enc, views)
    assert X.shape == views.rgb.shape[:3] + (64,) and X.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(X, axis=-1), 1.0, atol=1e-5)
    assert X.reshape(-1, 64).std(axis=0).max() > 1e-3  # features vary over the image


def test_dinov2_checkpoint_from_environment(tmp_path, monkeypatch):
    path = tmp_path / "from_env.pth"
    torch.save(_tiny_vit().state_dict(), path)
    monkeypatch.setenv(ENV_CHECKPOINT, str(path))
    assert DinoV2Encoder().checkpoint == path
    from dfd import encoders

    assert encoders.DinoV2Encoder is DinoV2Encoder  # the protocol's module exposes it too


def test_dinov2_missing_checkpoint_says_where(tmp_path, monkeypatch):
    monkeypatch.delenv(ENV_CHECKPOINT, raising=False)
    missing = tmp_path / "nowhere.pth"
    with pytest.raises(MissingCheckpointError, match=ENV_CHECKPOINT) as info:
        DinoV2Encoder(checkpoint=missing)
    assert str(missing) in str(info.value) and "never downloads" in str(info.value)


def test_dinov2_rejects_foreign_state_dict(tmp_path):
    path = tmp_path / "other.pth"
    torch.save({"weight": torch.zeros(3)}, path)
    with pytest.raises(DfdInputError, match="not a DINOv2"):
        load_dinov2(path)


def test_distill_with_a_dinov2_checkpoint(tmp_path):
    from dfd.distill import distill
    from dfd.shapes import icosphere

    path = tmp_path / "tiny_dinov2.pth"
    torch.save(_tiny_vit().state_dict(), path)
    V, F = icosphere(2)
    field = distill(
        V, F, encoder="dinov2", encoder_kwargs={"checkpoint": path, "num_heads": 2},
        n_views=3, resolution=28, steps=3, batch_size=64,
    )
    assert field.feature_dim == 64 and field.settings["encoder"]["name"] == "dinov2"
    np.testing.assert_allclose(np.linalg.norm(field.evaluate(V), axis=1), 1.0, atol=1e-5)
