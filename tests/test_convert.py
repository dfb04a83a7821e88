"""``rigmix convert``: any readable character file to USD or glTF (issue 7)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import asset
from pxr import Usd, UsdGeom, UsdSkel
from test_usd import decorated_chain, validation_errors

from rigmix.character import Character, Skeleton
from rigmix.errors import RigmixError
from rigmix.io import load_character
from rigmix.io.convert import convert, save_character
from rigmix.io.gltf import write_gltf


def test_glb_to_usda_keeps_joints_clips_and_texture(tmp_path):
    src = asset("CesiumMan")
    out = tmp_path / "cesium.usda"
    ch = convert(src, out)
    assert validation_errors(out) == []
    stage = Usd.Stage.Open(str(out))
    skel = next(p for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    assert list(skel.GetCustomDataByKey("rigmix:jointNames")) == list(ch.skeleton.names)
    assert [p.GetCustomDataByKey("rigmix:clipName") for p in stage.Traverse() if p.IsA(UsdSkel.Animation)] == \
        [c.name for c in ch.clips]
    (texture,) = (tmp_path / "textures").iterdir()
    assert texture.read_bytes() == ch.materials[0].base_color_texture.data


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_glb_to_gltf_round_trip(tmp_path, suffix):
    """Horse (13 clips, 5 roots) through convert: names, counts and clips survive."""
    src = asset("Horse")
    out = tmp_path / f"horse{suffix}"
    ch = convert(src, out)
    back = load_character(out)
    assert back.skeleton.names == ch.skeleton.names
    assert [c.name for c in back.clips] == [c.name for c in ch.clips]
    assert [len(m.positions) for m in back.meshes] == [len(m.positions) for m in ch.meshes]
    np.testing.assert_allclose(back.skeleton.inverse_binds, ch.skeleton.inverse_binds, atol=1e-5)


def test_static_character_converts_to_usd(tmp_path):
    """A file without a skin is a character too: its meshes become plain USD meshes."""
    deco = decorated_chain()
    static = Character("statue", Skeleton((), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)),
                                          np.zeros((0, 3)), np.zeros((0, 4, 4))),
                       props=(deco.props[1],), materials=deco.materials)
    src = tmp_path / "statue.glb"
    write_gltf(static, src)
    out = tmp_path / "statue.usdc"
    convert(src, out)
    assert validation_errors(out) == []
    stage = Usd.Stage.Open(str(out))
    (mesh,) = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    l2w = np.array(mesh.ComputeLocalToWorldTransform(0))
    P = np.array(mesh.GetPointsAttr().Get()) @ l2w[:3, :3] + l2w[3, :3]
    np.testing.assert_allclose(P, 2 * deco.props[1].mesh.positions, atol=1e-6)


def test_bad_targets_are_clear_errors(tmp_path):
    src = asset("SimpleSkin")
    with pytest.raises(RigmixError, match=r"out\.obj.*supported: \.glb"):
        convert(src, tmp_path / "out.obj")
    with pytest.raises(RigmixError, match="both the input and the output"):
        convert(src, src)
    with pytest.raises(RigmixError, match="missing.glb"):
        convert(tmp_path / "missing.glb", tmp_path / "out.usda")
    with pytest.raises(RigmixError, match="cannot write format"):
        save_character(load_character(src), tmp_path / "x.fbx")
    assert list(tmp_path.iterdir()) == []


def test_usd_back_to_glb_is_valid_and_poses_the_same(tmp_path):
    """glb -> usdc -> glb: the Khronos validator finds no error and every frame poses the same."""
    from test_usd import posed_error

    from rigmix.animation import clip_times
    from rigmix.io.validator import validate_gltf, validator_available

    usd = tmp_path / "knight.usdc"
    original = convert(asset("Knight"), usd)
    glb = tmp_path / "knight.glb"
    convert(usd, glb)
    back = load_character(glb)
    assert back.skeleton.names == original.skeleton.names
    assert [c.name for c in back.clips] == [c.name for c in original.clips]
    assert posed_error(original, back, clip_times) < 1e-5
    if validator_available():
        report = validate_gltf(glb)
        assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]


def test_cli_convert(tmp_path, capsys):
    from rigmix.cli import main

    out = tmp_path / "fox.usdc"
    assert main(["convert", str(asset("Fox")), str(out)]) == 0
    assert "24 joints" in capsys.readouterr().out and validation_errors(out) == []
    assert main(["convert", str(asset("Fox")), str(tmp_path / "fox.obj")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("rigmix: error: convert: fox.obj") and ".usdz" in err[0]
    assert main(["convert", str(tmp_path / "none.glb"), str(tmp_path / "x.usda")]) == 2
    assert "none.glb" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fox.usdc", "textures"]
