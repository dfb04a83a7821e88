"""USD export: UsdSkel's own skinning of the written file agrees with ours (issue 2, acceptance 3)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdSkel

from rigmix.animation import clip_times, sample_clip
from rigmix.character import Anchor, Clip, Skeleton, Track
from rigmix.io.gltf import read_gltf
from rigmix.io.usd import joint_paths, write_usd
from rigmix.errors import RigmixError
from rigmix.skinning import rest_pose, skin_character

from conftest import asset
from test_skinning import chain_character


def usd_skinned_world(path, times):
    """UsdSkel's skinned points of every skinned mesh, in world space, ``list of (F, n, 3)``.

    ``SkinningQuery.ComputeSkinnedPoints`` gives skeleton-space points; they are mapped to
    world space with the Skeleton prim's local-to-world transform at the same time.
    """
    stage = Usd.Stage.Open(str(path))
    fps = stage.GetTimeCodesPerSecond()
    root = UsdSkel.Root(stage.GetDefaultPrim())
    assert root, "the default prim must be the SkelRoot"
    cache = UsdSkel.Cache()
    cache.Populate(root, Usd.TraverseInstanceProxies())
    skel = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    skel_query = cache.GetSkelQuery(skel)
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and p.HasAPI(UsdSkel.BindingAPI)]
    out = [[] for _ in meshes]
    for t in times:
        code = Usd.TimeCode(float(t * fps))
        xforms = skel_query.ComputeSkinningTransforms(code)
        l2w = np.array(UsdGeom.Xformable(skel.GetPrim()).ComputeLocalToWorldTransform(code))
        for i, prim in enumerate(meshes):
            points = UsdGeom.Mesh(prim).GetPointsAttr().Get(code)
            assert cache.GetSkinningQuery(prim).ComputeSkinnedPoints(xforms, points, code)
            P = np.array(points, dtype=np.float64)
            out[i].append(P @ l2w[:3, :3] + l2w[3, :3])  # USD matrices act on row vectors
    return [np.array(o) for o in out]


def ours_world(character, clip, times, half_scales=False):
    T, R, S = sample_clip(character.skeleton, clip, times)
    if half_scales:  # SkelAnimation.scales is half3[] in the schema
        S = S.astype(np.float16).astype(np.float64)
    return [U for U, m in zip(skin_character(character, T, R, S), character.meshes) if m.skinned]


def assert_usd_matches(character, path, clip, times, rel=1e-5, half_scales=False):
    """Write ``clip``, skin with UsdSkel and with rigmix at ``times``; error / diagonal.

    The diagonal is that of our skinned points over all the frames (world space: bind-space
    positions can be on another scale, e.g. the Quaternius rigs' ``x100`` armature).
    """
    write_usd(character, path, clip=clip)
    usd = usd_skinned_world(path, times)
    ours = ours_world(character, clip, times, half_scales)
    assert len(usd) == len(ours) > 0
    allpts = np.concatenate([o.reshape(-1, 3) for o in ours])
    diag = np.linalg.norm(allpts.max(axis=0) - allpts.min(axis=0))
    worst = max(np.abs(u - o).max() for u, o in zip(usd, ours))
    assert worst <= rel * diag, f"UsdSkel vs rigmix: {worst:.3g} > {rel} x diagonal {diag:.3g}"
    return worst / diag


def ten_times(clip, fps=30.0):
    """Ten of the times the exporter writes (the clip's 1/fps grid, first and last included).

    Between written samples USD interpolates the samples themselves (lerp, slerp), which is a
    resampling of the clip, not a skinning difference; so the comparison is made on the grid.
    """
    t = clip_times(clip, fps)
    return t[np.linspace(0, len(t) - 1, 10).round().astype(int)]


def two_anchor_character():
    """The chain plus a second root joint hanging from a different anchor (folding case)."""
    ch = chain_character(anchor=True)
    sk = ch.skeleton
    anchors = sk.anchors + (Anchor("Other", np.array(
        [[0.0, -1, 0, 0.3], [1, 0, 0, 0.1], [0, 0, 1, -0.2], [0, 0, 0, 1]])),)
    sk2 = Skeleton(
        sk.names + ("ik.L",), np.append(sk.parents, -1), np.vstack([sk.translations, [0.2, 0.5, 0.1]]),
        np.vstack([sk.rotations, [0, 0.3826834, 0, 0.9238795]]), np.vstack([sk.scales, [1, 1, 1]]),
        np.eye(4)[None].repeat(4, 0), anchors, np.append(sk.root_anchor, 2),
    )
    sk2 = replace(sk2, inverse_binds=np.linalg.inv(sk2.rest_worlds()))
    mesh = ch.meshes[0]
    J, W = mesh.joints.copy(), mesh.weights.copy()
    sel = np.arange(0, len(J), 3)
    J[sel, 2] = 3
    W[sel, 2] = 0.4
    W /= W.sum(axis=1, keepdims=True)
    clip = ch.clips[0]
    tracks = clip.tracks + (Track(3, "translation", [0.0, 1.5], [[0.2, 0.5, 0.1], [0.6, 0.2, 0.1]]),
                            Track(3, "rotation", [0.0, 1.5], [[0, 0.3826834, 0, 0.9238795], [0, 0, 0, 1]]))
    return replace(ch, skeleton=sk2, meshes=(replace(mesh, joints=J, weights=W),),
                   clips=(Clip(clip.name, tracks),))


def test_chain_with_anchor_matches_usdskel(tmp_path):
    ch = chain_character(anchor=True)
    clip = ch.clips[0]
    # the clip's cubic scale track is not exact in half precision: compare with rounded scales
    err = assert_usd_matches(ch, tmp_path / "chain.usda", clip, ten_times(clip), half_scales=True)
    assert err < 1e-6
    # without the scale track nothing is rounded but float32
    rigid = Clip("rigid", tuple(t for t in clip.tracks if t.path != "scale"))
    assert assert_usd_matches(ch, tmp_path / "rigid.usda", rigid, ten_times(clip)) < 1e-6
    # and the rounding of scales is the only loss: about half precision (2^-11) of the extent
    assert assert_usd_matches(ch, tmp_path / "chain.usda", clip, ten_times(clip), rel=1e-3) > 1e-6


def test_roots_with_different_anchors_are_folded(tmp_path):
    ch = two_anchor_character()
    path = tmp_path / "two.usdc"
    assert_usd_matches(ch, path, ch.clips[0], ten_times(ch.clips[0]), half_scales=True)
    stage = Usd.Stage.Open(str(path))
    root = stage.GetDefaultPrim()
    assert np.allclose(np.array(UsdGeom.Xformable(root).ComputeLocalToWorldTransform(0)), np.eye(4))


def test_stage_metadata_and_skeleton(tmp_path):
    ch = chain_character(anchor=True)
    path = tmp_path / "chain.usda"
    write_usd(ch, path)
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 30.0
    root = stage.GetDefaultPrim()
    assert root.IsA(UsdSkel.Root)
    # the shared anchor world is the SkelRoot's transform (row vectors in USD)
    A = ch.skeleton.anchor_worlds()[1]
    np.testing.assert_allclose(np.array(UsdGeom.Xformable(root).ComputeLocalToWorldTransform(0)), A.T, atol=1e-12)
    skel = UsdSkel.Skeleton(root.GetChild("Skeleton"))
    assert list(skel.GetJointsAttr().Get()) == ["root", "root/mid", "root/mid/tip"]
    assert list(skel.GetPrim().GetCustomDataByKey("rigmix:jointNames")) == list(ch.skeleton.names)
    # rest transforms: our column-vector locals, transposed
    rest = np.array(skel.GetRestTransformsAttr().Get())
    np.testing.assert_allclose(np.swapaxes(rest, 1, 2), ch.skeleton.rest_locals(), atol=1e-12)
    # bind transforms in skel space: A^-1 @ inverse(inverse_bind)
    bind = np.swapaxes(np.array(skel.GetBindTransformsAttr().Get()), 1, 2)
    np.testing.assert_allclose(A @ bind @ ch.skeleton.inverse_binds, np.eye(4)[None].repeat(3, 0), atol=1e-12)
    # animation: quaternions converted from xyzw to GfQuatf (w, x, y, z)
    anim = UsdSkel.Animation(root.GetChild("Animation"))
    t = clip_times(ch.clips[0])
    _, R, _ = sample_clip(ch.skeleton, ch.clips[0], t)
    for f in (0, 7, len(t) - 1):
        q = anim.GetRotationsAttr().Get(Usd.TimeCode(t[f] * 30))
        got = np.array([[r.GetImaginary()[0], r.GetImaginary()[1], r.GetImaginary()[2], r.GetReal()] for r in q])
        np.testing.assert_allclose(got, R[f], atol=1e-6)
    mesh = UsdGeom.Mesh(root.GetChild("tube"))
    binding = UsdSkel.BindingAPI(mesh.GetPrim())
    assert binding.GetJointIndicesPrimvar().GetElementSize() == 4
    assert binding.GetJointWeightsPrimvar().GetElementSize() == 4
    assert np.array_equal(np.array(binding.GetGeomBindTransformAttr().Get()), np.eye(4))


def test_joint_paths_are_valid_and_unique():
    names = ("Hips", "Foot.L", "Foot_L", "1st joint", "Foot.L_2", "")
    sk = Skeleton(names, [-1, 0, 0, 1, 0, 4], np.zeros((6, 3)), np.tile([0, 0, 0, 1.0], (6, 1)),
                  np.ones((6, 3)), np.eye(4)[None].repeat(6, 0))
    paths = joint_paths(sk)
    assert len(set(paths)) == 6
    for p in paths:
        assert Sdf.Path.IsValidPathString(p)
    assert paths[1] == "Hips/Foot_L" and paths[2] == "Hips/Foot_L_2" and paths[4] == "Hips/Foot_L_2_2"
    assert paths[5].startswith("Hips/Foot_L_2_2/")


# ---------------------------------------------------------------------------------------------
# real characters (acceptance 3)


@pytest.mark.parametrize("name", ["CesiumMan", "Fox", "Horse"])
def test_real_character_matches_usdskel(tmp_path, name):
    """CesiumMan: Z_UP matrix anchor; Fox: centimetres; Horse: 5 roots under a x100 armature."""
    ch = read_gltf(asset(name))
    clip = ch.clips[-1]
    # measured: CesiumMan 2e-7, Fox 8e-8 (float32 in USD), Horse 2e-6 (its rest scales such as
    # 1.000011 are rounded by SkelAnimation's half3 scales)
    assert_usd_matches(ch, tmp_path / f"{name}.usdc", clip, ten_times(clip))


@pytest.mark.parametrize("make", [lambda: chain_character(anchor=True), two_anchor_character])
def test_without_clip_usdskel_skins_the_rest_pose(tmp_path, make):
    """No SkelAnimation: UsdSkel uses restTransforms (roots folded or not) = our rest pose."""
    ch = replace(make(), clips=())
    path = tmp_path / "rest.usda"
    write_usd(ch, path)
    stage = Usd.Stage.Open(str(path))
    assert not any(p.IsA(UsdSkel.Animation) for p in stage.Traverse())
    (usd,) = usd_skinned_world(path, [0.0])
    (ours,) = rest_pose(ch)
    np.testing.assert_allclose(usd[0], ours, atol=1e-6)


def test_clip_chosen_by_name_and_unknown_name_is_an_error(tmp_path):
    ch = chain_character()
    ch = replace(ch, clips=(Clip("still", ()),) + ch.clips)
    path = tmp_path / "named.usda"
    write_usd(ch, path, clip="bend")
    stage = Usd.Stage.Open(str(path))
    anim = UsdSkel.Animation(stage.GetDefaultPrim().GetChild("Animation"))
    assert anim.GetPrim().GetCustomDataByKey("rigmix:clipName") == "bend"
    with pytest.raises(RigmixError, match="no clip 'run'"):
        write_usd(ch, tmp_path / "bad.usda", clip="run")
