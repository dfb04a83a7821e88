"""USD export: UsdSkel's own skinning of the written file agrees with ours on every clip,
UsdValidation finds no error, and the file keeps names, counts, materials and textures
(issue 7, acceptance 3)."""

from __future__ import annotations

import os
import zipfile
from dataclasses import replace

import numpy as np
import pytest
from conftest import IN_COMPOSED_GROUP, ROOT, asset
from pxr import Sdf, Usd, UsdGeom, UsdShade, UsdSkel, UsdValidation
from test_skinning import chain_character

from rigmix.animation import clip_times, sample_clip
from rigmix.character import Anchor, Character, Clip, Material, Mesh, Prop, Skeleton, Texture, Track
from rigmix.errors import RigmixError
from rigmix.io.gltf import read_gltf
from rigmix.io.usd import joint_paths, write_usd
from rigmix.skinning import rest_pose, skin_character

# ---------------------------------------------------------------------------------------------
# helpers


def validation_errors(path):
    """``(name, message)`` of every UsdValidation error on the stage, all validators."""
    stage = Usd.Stage.Open(str(path))
    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    return [(e.GetName(), e.GetMessage()) for e in ctx.Validate(stage)
            if e.GetType() == UsdValidation.ValidationErrorType.Error]


def select_clip(stage, variant):
    """Select an ``animation`` variant of the Skeleton in the session layer."""
    skel = next(p for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    with Usd.EditContext(stage, stage.GetSessionLayer()):
        skel.GetVariantSets().GetVariantSet("animation").SetVariantSelection(variant)


def usd_skinned_world(stage, times, meshes=None):
    """UsdSkel's skinned points of the skinned meshes at ``times``, world space, ``list of (F, n, 3)``.

    ``SkinningQuery.ComputeSkinnedPoints`` gives skeleton-space points; they are mapped to
    world space with the Skeleton prim's local-to-world transform at the same time.
    """
    fps = stage.GetTimeCodesPerSecond()
    root = UsdSkel.Root(stage.GetDefaultPrim())
    assert root, "the default prim must be the SkelRoot"
    cache = UsdSkel.Cache()
    cache.Populate(root, Usd.TraverseInstanceProxies())
    skel = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    skel_query = cache.GetSkelQuery(skel)
    if meshes is None:
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


def relative_error(usd, ours):
    """Max |UsdSkel - rigmix| over all points and frames / diagonal of our skinned points.

    The diagonal is that of our skinned points over all the frames (world space: bind-space
    positions can be on another scale, e.g. the Quaternius rigs' ``x100`` armature).
    """
    assert len(usd) == len(ours) > 0
    allpts = np.concatenate([o.reshape(-1, 3) for o in ours])
    diag = np.linalg.norm(allpts.max(axis=0) - allpts.min(axis=0))
    return max(np.abs(u - o).max() for u, o in zip(usd, ours)) / diag


def assert_usd_matches(character, path, clip, times, rel=1e-5, half_scales=False):
    """Write ``clip`` alone, skin with UsdSkel and with rigmix at ``times``; error / diagonal."""
    write_usd(character, path, clips=[clip])
    err = relative_error(usd_skinned_world(Usd.Stage.Open(str(path)), times),
                         ours_world(character, clip, times, half_scales))
    assert err <= rel, f"UsdSkel vs rigmix: {err:.3g} x diagonal > {rel}"
    return err


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


# ---------------------------------------------------------------------------------------------
# synthetic characters with known answers


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
    assert validation_errors(path) == []


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
    assert list(skel.GetJointNamesAttr().Get()) == list(ch.skeleton.names)
    assert list(skel.GetPrim().GetCustomDataByKey("rigmix:jointNames")) == list(ch.skeleton.names)
    # rest transforms: our column-vector locals, transposed
    rest = np.array(skel.GetRestTransformsAttr().Get())
    np.testing.assert_allclose(np.swapaxes(rest, 1, 2), ch.skeleton.rest_locals(), atol=1e-12)
    # bind transforms in skel space: A^-1 @ inverse(inverse_bind)
    bind = np.swapaxes(np.array(skel.GetBindTransformsAttr().Get()), 1, 2)
    np.testing.assert_allclose(A @ bind @ ch.skeleton.inverse_binds, np.eye(4)[None].repeat(3, 0), atol=1e-12)
    # animation: quaternions converted from xyzw to GfQuatf (w, x, y, z)
    anim = UsdSkel.Animation(root.GetChild("Animations").GetChild("bend"))
    assert UsdSkel.BindingAPI(skel.GetPrim()).GetAnimationSourceRel().GetTargets() == [anim.GetPath()]
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
    np.testing.assert_array_equal(np.array(binding.GetJointIndicesPrimvar().Get()).reshape(-1, 4), ch.meshes[0].joints)
    assert np.array_equal(np.array(binding.GetGeomBindTransformAttr().Get()), np.eye(4))
    assert validation_errors(path) == []


def test_the_validator_reports_missing_metadata(tmp_path):
    """The check used on every written file is live: a bare stage has 3 errors."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "bare.usda"))
    UsdGeom.Mesh.Define(stage, "/mesh")
    stage.GetRootLayer().Save()
    names = {name for name, _ in validation_errors(tmp_path / "bare.usda")}
    assert {"MissingDefaultPrim", "MissingMetersPerUnitMetadata", "MissingUpAxisMetadata"} <= names


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


@pytest.mark.parametrize("make", [lambda: chain_character(anchor=True), two_anchor_character])
def test_without_clip_usdskel_skins_the_rest_pose(tmp_path, make):
    """No SkelAnimation: UsdSkel uses restTransforms (roots folded or not) = our rest pose."""
    ch = replace(make(), clips=())
    path = tmp_path / "rest.usda"
    write_usd(ch, path)
    stage = Usd.Stage.Open(str(path))
    assert not any(p.IsA(UsdSkel.Animation) for p in stage.Traverse())
    (usd,) = usd_skinned_world(stage, [0.0])
    (ours,) = rest_pose(ch)
    np.testing.assert_allclose(usd[0], ours, atol=1e-6)


def two_clip_chain():
    ch = chain_character()
    wave = Clip("wave|2", (Track(1, "rotation", [0.5, 1.0, 2.0],
                                 [[0, 0, 0, 1], [0.3826834, 0, 0, 0.9238795], [0, 0.5, 0, 0.8660254]]),))
    return replace(ch, clips=ch.clips + (wave,))


def test_every_clip_is_a_variant_and_a_kept_prim(tmp_path):
    ch = two_clip_chain()
    path = tmp_path / "two.usda"
    write_usd(ch, path, default_clip="wave|2")
    stage = Usd.Stage.Open(str(path))
    root = stage.GetDefaultPrim()
    assert list(root.GetCustomDataByKey("rigmix:clipNames")) == ["bend", "wave|2"]
    anims = [p for p in stage.Traverse() if p.IsA(UsdSkel.Animation)]
    assert [p.GetCustomDataByKey("rigmix:clipName") for p in anims] == ["bend", "wave|2"]
    skel = root.GetChild("Skeleton")
    vset = skel.GetVariantSets().GetVariantSet("animation")
    assert vset.GetVariantNames() == sorted(p.GetName() for p in anims)
    assert vset.GetVariantSelection() == anims[1].GetName()  # the default clip asked for
    assert stage.GetStartTimeCode() == 0.0 and stage.GetEndTimeCode() == 60.0
    for anim, clip in zip(anims, ch.clips):
        select_clip(stage, anim.GetName())
        assert UsdSkel.BindingAPI(skel).GetAnimationSourceRel().GetTargets() == [anim.GetPath()]
        times = ten_times(clip)
        err = relative_error(usd_skinned_world(stage, times), ours_world(ch, clip, times, half_scales=True))
        assert err < 1e-6, (clip.name, err)
    # the two clips pose the chain differently at the same time: the variant really switches
    select_clip(stage, anims[0].GetName())
    (a,) = usd_skinned_world(stage, [1.0])
    select_clip(stage, anims[1].GetName())
    (b,) = usd_skinned_world(stage, [1.0])
    assert np.abs(a - b).max() > 0.05
    assert validation_errors(path) == []


def test_clip_subset_by_name_and_unknown_name_is_an_error(tmp_path):
    ch = two_clip_chain()
    path = tmp_path / "named.usda"
    write_usd(ch, path, clips=["wave|2"])
    stage = Usd.Stage.Open(str(path))
    anims = [p for p in stage.Traverse() if p.IsA(UsdSkel.Animation)]
    assert [p.GetCustomDataByKey("rigmix:clipName") for p in anims] == ["wave|2"]
    with pytest.raises(RigmixError, match="no clip 'run'"):
        write_usd(ch, tmp_path / "bad.usda", clips=["run"])
    with pytest.raises(RigmixError, match="suffix"):
        write_usd(ch, tmp_path / "bad.obj")
    assert not (tmp_path / "bad.usda").exists()


def checker_png():
    import io

    from PIL import Image

    img = Image.new("RGBA", (4, 4), (255, 0, 0, 255))
    img.putpixel((0, 0), (0, 0, 255, 128))
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


def decorated_chain():
    """The chain with uvs, normals, vertex colours, a textured BLEND material and two props."""
    ch = chain_character()
    mesh = ch.meshes[0]
    rng = np.random.default_rng(7)
    n = len(mesh.positions)
    uv = rng.random((n, 2))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    colors = np.column_stack([rng.random((n, 3)), np.linspace(0.2, 1.0, n)])
    tex = Texture(checker_png(), "image/png", "checker", {"wrapS": 33071, "wrapT": 33648})
    mats = (Material("skin", np.array([0.5, 0.8, 1.0, 0.9]), 0.1, 0.7, tex, alpha_mode="BLEND",
                     double_sided=True),
            Material("metal.flat", np.array([0.2, 0.3, 0.4, 1.0]), 1.0, 0.2))
    mesh = replace(mesh, uvs=(uv,), normals=normals, colors=colors, material=0)
    box_v = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (0, 0.5) for z in (-0.05, 0.05)])
    box_f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    sword = Mesh("sword", box_v, box_f, material=1)
    grip = np.array([[0, -1, 0, 0.1], [1, 0, 0, 0.2], [0, 0, 1, 0.0], [0, 0, 0, 1]], dtype=float)
    props = (Prop(sword, 2, grip), Prop(replace(sword, name="rock"), -1, np.diag([2.0, 2.0, 2.0, 1.0])))
    return replace(ch, meshes=(mesh,), materials=mats, props=props)


def test_materials_textures_props_and_primvars(tmp_path):
    ch = decorated_chain()
    path = tmp_path / "deco.usda"
    write_usd(ch, path)
    assert validation_errors(path) == []
    stage = Usd.Stage.Open(str(path))
    root = stage.GetDefaultPrim()
    tube = UsdGeom.Mesh(root.GetChild("tube"))
    pv = UsdGeom.PrimvarsAPI(tube)
    st = pv.GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.vertex
    np.testing.assert_allclose(np.array(st.Get()), np.column_stack([ch.meshes[0].uvs[0][:, 0],
                                                                   1 - ch.meshes[0].uvs[0][:, 1]]), atol=1e-6)
    np.testing.assert_allclose(np.array(tube.GetDisplayColorPrimvar().Get()), ch.meshes[0].colors[:, :3], atol=1e-6)
    np.testing.assert_allclose(np.array(tube.GetDisplayOpacityPrimvar().Get()), ch.meshes[0].colors[:, 3], atol=1e-6)
    # normals in skeleton space: the SkelRoot's transform maps them back to ours
    A = ch.skeleton.anchor_worlds()[1][:3, :3]
    N = np.array(tube.GetNormalsAttr().Get()) @ A.T
    np.testing.assert_allclose(N, ch.meshes[0].normals, atol=1e-6)
    assert tube.GetDoubleSidedAttr().Get() is True
    # material: texture scaled by the base colour factor, alpha from the texture (BLEND)
    mat, _ = UsdShade.MaterialBindingAPI(tube.GetPrim()).ComputeBoundMaterial()
    assert mat.GetPrim().GetCustomDataByKey("rigmix:name") == "skin"
    surf = UsdShade.Shader(mat.GetPrim().GetChild("PreviewSurface"))
    texture = UsdShade.Shader(mat.GetPrim().GetChild("BaseColorTexture"))
    assert surf.GetInput("diffuseColor").GetConnectedSources()[0][0].sourceName == "rgb"
    assert surf.GetInput("opacity").GetConnectedSources()[0][0].sourceName == "a"
    np.testing.assert_allclose(np.array(texture.GetInput("scale").Get()), [0.5, 0.8, 1.0, 0.9], atol=1e-7)
    assert texture.GetInput("wrapS").Get() == "clamp" and texture.GetInput("wrapT").Get() == "mirror"
    file = texture.GetInput("file").Get()
    assert (tmp_path / file.path).read_bytes() == ch.materials[0].base_color_texture.data
    assert os.path.samefile(file.resolvedPath, tmp_path / "textures" / "chain_checker.png")
    # the untextured material: flat colour
    flat = UsdShade.Shader(root.GetChild("Materials").GetChild("metal_flat").GetChild("PreviewSurface"))
    np.testing.assert_allclose(np.array(flat.GetInput("diffuseColor").Get()), [0.2, 0.3, 0.4], atol=1e-7)
    assert flat.GetInput("metallic").Get() == 1.0
    # the prop on joint 'tip' is rigidly skinned: UsdSkel gives world[tip] @ grip @ p at every time
    sword = root.GetChild("prop_sword")
    binding = UsdSkel.BindingAPI(sword)
    assert binding.GetJointIndicesPrimvar().GetInterpolation() == UsdGeom.Tokens.constant
    assert list(binding.GetJointIndicesPrimvar().Get()) == [2]
    clip = ch.clips[0]
    times = ten_times(clip)
    (usd,) = usd_skinned_world(stage, times, meshes=[sword])
    T, R, S = sample_clip(ch.skeleton, clip, times)
    S = S.astype(np.float16).astype(np.float64)
    from rigmix.transforms import trs_to_matrix
    world = ch.skeleton.world_matrices(trs_to_matrix(T, R, S))[:, 2] @ ch.props[0].matrix  # (F, 4, 4)
    ours = np.einsum("fij,nj->fni", world[:, :3, :3], ch.props[0].mesh.positions) + world[:, None, :3, 3]
    np.testing.assert_allclose(usd, ours, atol=1e-5)
    # the static prop: its matrix in world space
    rock = UsdGeom.Mesh(root.GetChild("prop_rock"))
    l2w = np.array(rock.ComputeLocalToWorldTransform(0))
    P = np.array(rock.GetPointsAttr().Get()) @ l2w[:3, :3] + l2w[3, :3]
    np.testing.assert_allclose(P, 2 * box_points(ch), atol=1e-6)


def box_points(ch):
    return ch.props[1].mesh.positions


def test_static_character_without_joints(tmp_path):
    ch = decorated_chain()
    static = Character("statue", Skeleton((), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)),
                                         np.zeros((0, 4, 4))),
                       props=(ch.props[1],), materials=ch.materials)
    path = tmp_path / "statue.usdc"
    write_usd(static, path)
    stage = Usd.Stage.Open(str(path))
    assert stage.GetDefaultPrim().IsA(UsdGeom.Xform) and not stage.GetDefaultPrim().IsA(UsdSkel.Root)
    assert validation_errors(path) == []


def test_usdz_packages_the_textures(tmp_path):
    ch = decorated_chain()
    path = tmp_path / "deco.usdz"
    write_usd(ch, path)
    names = zipfile.ZipFile(path).namelist()
    assert names[0].endswith(".usdc") and "textures/chain_checker.png" in names
    assert not (tmp_path / "textures").exists()
    assert validation_errors(path) == []
    assert [p.name for p in tmp_path.iterdir()] == ["deco.usdz"]


def test_writing_is_atomic(tmp_path, monkeypatch):
    ch = chain_character()
    path = tmp_path / "atomic.usda"
    write_usd(ch, path)
    before = path.read_bytes()

    def failing_replace(src, dst):
        raise OSError("disk full")

    import rigmix.safety

    monkeypatch.setattr(rigmix.safety.os, "replace", failing_replace)  # the writers' final rename
    with pytest.raises(RigmixError, match="disk full"):
        write_usd(two_clip_chain(), path)
    monkeypatch.undo()
    assert path.read_bytes() == before  # the old file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["atomic.usda"]  # no temporary left
    # a target that cannot be replaced (a folder) is a RigmixError, and nothing is left either
    (tmp_path / "dir.usdc").mkdir()
    with pytest.raises(RigmixError, match="dir.usdc"):
        write_usd(ch, tmp_path / "dir.usdc")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["atomic.usda", "dir.usdc"]


# ---------------------------------------------------------------------------------------------
# real characters (acceptance 3)

REAL = ("CesiumMan", "RiggedFigure", "Knight", "Fox", "Horse", "Wasp", "Velociraptor", "SimpleSkin")


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """name -> (character, path of its .usdc with every clip), written once per module."""
    out = tmp_path_factory.mktemp("usd")
    cache = {}

    def get(name):
        if name not in cache:
            ch = read_gltf(asset(name))
            cache[name] = ch, write_usd(ch, out / f"{name}.usdc")
        return cache[name]

    return get


@pytest.mark.parametrize("name", REAL)
def test_real_character_is_valid_and_matches_usdskel_on_its_clips(written, name):
    """CesiumMan: Z_UP matrix anchor; Fox: centimetres; Horse: 5 roots under a x100 armature.

    Measured on every clip: about 2e-7 x diagonal (float32) on most, 2e-6 on the Quaternius rigs (rest scales
    such as 1.000011 are rounded by SkelAnimation's half3 scales).
    """
    ch, path = written(name)
    assert validation_errors(path) == []
    stage = Usd.Stage.Open(str(path))
    anims = [p for p in stage.Traverse() if p.IsA(UsdSkel.Animation)]
    assert [p.GetCustomDataByKey("rigmix:clipName") for p in anims] == [c.name for c in ch.clips]
    for i, clip in enumerate(ch.clips):  # every clip (Horse 13, Knight 12): about 1 s in all
        select_clip(stage, anims[i].GetName())
        times = ten_times(clip)
        err = relative_error(usd_skinned_world(stage, times), ours_world(ch, clip, times))
        assert err <= 1e-5, f"{name} clip {clip.name!r}: UsdSkel vs rigmix {err:.3g} x diagonal"


def test_cesiumman_reads_back_names_counts_and_texture(written):
    ch, path = written("CesiumMan")
    stage = Usd.Stage.Open(str(path))
    root = stage.GetDefaultPrim()
    skel = UsdSkel.Skeleton(root.GetChild("Skeleton"))
    assert list(skel.GetPrim().GetCustomDataByKey("rigmix:jointNames")) == list(ch.skeleton.names)
    assert list(skel.GetJointNamesAttr().Get()) == list(ch.skeleton.names)
    assert len(skel.GetJointsAttr().Get()) == ch.skeleton.num_joints
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert len(meshes) == len(ch.meshes) == 1
    mesh, src = meshes[0], ch.meshes[0]
    assert mesh.GetPrim().GetCustomDataByKey("rigmix:name") == src.name
    assert len(mesh.GetPointsAttr().Get()) == len(src.positions)
    np.testing.assert_array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), src.faces)
    st = np.array(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").Get())
    np.testing.assert_allclose(st, np.column_stack([src.uvs[0][:, 0], 1 - src.uvs[0][:, 1]]), atol=1e-6)
    mat, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    assert mat.GetPrim().GetCustomDataByKey("rigmix:name") == ch.materials[0].name
    tex = UsdShade.Shader(mat.GetPrim().GetChild("BaseColorTexture"))
    assert tex.GetIdAttr().Get() == "UsdUVTexture"
    file = tex.GetInput("file").Get()
    assert file.resolvedPath.endswith(".jpg")
    with open(file.resolvedPath, "rb") as fh:
        assert fh.read() == ch.materials[0].base_color_texture.data
    reader = tex.GetInput("st").GetConnectedSources()[0][0].source
    assert UsdShade.Shader(reader).GetInput("varname").Get() == "st"


# ---------------------------------------------------------------------------------------------
# reading back (rigmix.io.usd_read)


def posed_error(a, b, times_of):
    """Max over clips, frames and meshes (props included) of |a - b| / diagonal of a's poses."""
    from rigmix.preview.render import pose_scene

    worst = 0.0
    for ca, cb in zip(a.clips, b.clips):
        t = times_of(ca)
        pa, pb = pose_scene(a, ca, t).positions, pose_scene(b, cb, t).positions
        assert [p.shape for p in pa] == [p.shape for p in pb]
        pts = np.concatenate([p.reshape(-1, 3) for p in pa])
        diag = np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))
        worst = max(worst, max(np.abs(p - q).max() for p, q in zip(pa, pb)) / diag)
    return worst


@pytest.mark.parametrize("name", ["CesiumMan", "Horse"])
def test_read_back_reproduces_the_character(written, name):
    """write_usd then read_usd: names, hierarchy, counts, materials, textures, every clip's poses."""
    from rigmix.io import load_character

    ch, path = written(name)
    back = load_character(path)
    assert back.skeleton.names == ch.skeleton.names
    np.testing.assert_array_equal(back.skeleton.parents, ch.skeleton.parents)
    assert back.warnings == ()  # vertex-interpolated primvars: nothing split, order kept
    assert [m.name for m in back.meshes] == [m.name for m in ch.meshes]
    for m, n in zip(ch.meshes, back.meshes):
        np.testing.assert_array_equal(n.faces, m.faces)
        np.testing.assert_array_equal(n.joints, m.joints)
        np.testing.assert_allclose(n.weights, m.weights, atol=1e-7)
        assert n.material == m.material and len(n.uvs) == len(m.uvs)
        for u, v in zip(m.uvs, n.uvs):
            np.testing.assert_allclose(v, u, atol=1e-6)
    assert [m.name for m in back.materials] == [m.name for m in ch.materials]
    for m, n in zip(ch.materials, back.materials):
        np.testing.assert_allclose(n.base_color, m.base_color, atol=1e-7)
        assert (n.base_color_texture is None) == (m.base_color_texture is None)
        if m.base_color_texture is not None:
            assert n.base_color_texture.data == m.base_color_texture.data
            assert n.base_color_texture.mime_type == m.base_color_texture.mime_type
    assert [c.name for c in back.clips] == [c.name for c in ch.clips]
    # every frame of every clip (float32 and half scales: measured 2e-7, Horse 2e-6)
    assert posed_error(ch, back, clip_times) < 1e-5


def test_usdz_round_trip_keeps_props_textures_and_colours(tmp_path):
    from rigmix.io import load_character

    ch = decorated_chain()
    write_usd(ch, tmp_path / "deco.usdz")
    back = load_character(tmp_path / "deco.usdz")
    assert back.materials[0].base_color_texture.data == ch.materials[0].base_color_texture.data  # inside the zip
    assert back.materials[0].alpha_mode == "BLEND" and back.materials[1].alpha_mode == "OPAQUE"
    assert back.materials[0].double_sided and not back.materials[1].double_sided
    np.testing.assert_allclose(back.materials[0].base_color, ch.materials[0].base_color, atol=1e-7)
    assert [(p.mesh.name, p.joint) for p in back.props] == [("sword", 2), ("rock", -1)]
    np.testing.assert_allclose(back.meshes[0].colors, ch.meshes[0].colors, atol=1e-6)
    np.testing.assert_allclose(back.meshes[0].normals, ch.meshes[0].normals, atol=1e-6)
    # poses of the tube and both props; the clip's cubic scale track is rounded to half (2^-11)
    assert posed_error(ch, back, ten_times) < 1e-3


def test_read_face_varying_quads(tmp_path):
    """A hand-made UsdSkel file: quads fanned into triangles, faceVarying st split per corner."""
    from rigmix.io import load_character

    path = tmp_path / "quad.usda"
    stage = Usd.Stage.CreateNew(str(path))
    root = UsdSkel.Root.Define(stage, "/Quad")
    stage.SetDefaultPrim(root.GetPrim())
    skel = UsdSkel.Skeleton.Define(stage, "/Quad/Skel")
    skel.CreateJointsAttr(["a", "a/b"])
    eye = np.eye(4)
    lift = np.eye(4)
    lift[3, 1] = 1.0  # USD row vectors: translation in the last row
    from pxr import Gf, Vt

    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(eye.tolist()), Gf.Matrix4d(lift.tolist())]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(eye.tolist()), Gf.Matrix4d(lift.tolist())]))
    mesh = UsdGeom.Mesh.Define(stage, "/Quad/Mesh")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (2, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4, 4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 1, 4, 5, 2])
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
    st.Set([(0, 0), (1, 0), (1, 1), (0, 1), (0, 0), (0.5, 0), (0.5, 0.25), (0, 0.25)])
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 1).Set([0, 0, 1, 1, 0, 1])
    binding.CreateJointWeightsPrimvar(False, 1).Set([1.0] * 6)
    stage.GetRootLayer().Save()
    ch = load_character(path)
    assert ch.skeleton.names == ("a", "b") and list(ch.skeleton.parents) == [-1, 0]
    (m,) = ch.meshes
    assert m.positions.shape == (8, 3) and m.faces.shape == (4, 3)
    np.testing.assert_allclose(m.positions[m.faces[0]], [[0, 0, 0], [1, 0, 0], [1, 1, 0]])
    np.testing.assert_allclose(m.uvs[0][5], [0.5, 1.0])  # (s, 1 - t)
    np.testing.assert_array_equal(m.joints[:, 0], [0, 0, 1, 1, 0, 0, 1, 1])  # follows the corners
    assert len(ch.warnings) == 1 and "one per face corner" in ch.warnings[0]
    # the rest pose reproduces the points (bind = rest)
    np.testing.assert_allclose(rest_pose(ch)[0], m.positions, atol=1e-12)


@IN_COMPOSED_GROUP
def test_composed_centaur_keeps_every_clip_in_usd(tmp_path, composed):
    """End to end (issue 7): the built-in centaur's completed clips, by source name, in a valid USD
    file whose UsdSkel skinning matches ours on every clip."""
    ch = composed(ROOT / "examples" / "centaur.toml").character
    path = write_usd(ch, tmp_path / "centaur.usdc")
    assert validation_errors(path) == []
    stage = Usd.Stage.Open(str(path))
    anims = [p for p in stage.Traverse() if p.IsA(UsdSkel.Animation)]
    assert [p.GetCustomDataByKey("rigmix:clipName") for p in anims] == [c.name for c in ch.clips]
    assert len(ch.clips) >= 2
    for anim, clip in zip(anims, ch.clips):
        select_clip(stage, anim.GetName())
        t = ten_times(clip)
        assert relative_error(usd_skinned_world(stage, t), ours_world(ch, clip, t)) < 1e-5, clip.name
