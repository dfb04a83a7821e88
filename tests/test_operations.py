"""Output skeleton, provenance, scale matching and preliminary positioning (PIPELINE.md sec. 1)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import asset, corpus, corpus_case

from rigmix.animation import sample_clip
from rigmix.character import Character, Mesh, Skeleton
from rigmix.config import Config, load_config
from rigmix.errors import InputError
from rigmix.io import load_character
from rigmix.limbs import classify_limbs
from rigmix.operations import plan_operations
from rigmix.operations.positioning import (
    AGREEMENT,
    SPREAD_STEPS,
    chain_length,
    cut_section,
    facing_turn,
    limb_kind,
    pair_scale,
    part_weights,
    position_character,
    rebase,
    rest_world_faces,
    rest_world_mesh,
    skeleton_adjacency,
    smooth_translations,
    spread_to_surface,
)
from rigmix.pipeline import load_characters
from rigmix.skinning import linear_blend_skinning, rest_pose, skinning_matrices
from rigmix.sparse_weights import dense_rows
from rigmix.transforms import quat_to_matrix

CONFIGS = Path(__file__).parent / "configs"


# --------------------------------------------------------------------------------------------
# Fixtures
# --------------------------------------------------------------------------------------------


def toy(names, parents, positions, name="toy", tri=0.05):
    """A character with identity rest rotations and one small triangle (legs ``tri``) per joint, fully weighted."""
    P = np.asarray(positions, dtype=float)
    parents = np.asarray(parents)
    J = len(names)
    T = np.where(parents[:, None] >= 0, P - P[np.maximum(parents, 0)], P)
    ibm = np.tile(np.eye(4), (J, 1, 1))
    ibm[:, :3, 3] = -P
    sk = Skeleton(names, parents, T, np.tile([0, 0, 0, 1.0], (J, 1)), np.ones((J, 3)), ibm)
    V = np.concatenate([P + [tri, 0, 0], P + [0, tri, 0], P + [0, 0, tri]])
    F = np.stack([np.arange(J), np.arange(J) + J, np.arange(J) + 2 * J], axis=1)
    joints = np.zeros((3 * J, 4), dtype=int)
    joints[:, 0] = np.tile(np.arange(J), 3)
    weights = np.zeros((3 * J, 4))
    weights[:, 0] = 1
    return Character(name, sk, meshes=(Mesh("m", V, F, joints=joints, weights=weights),))


def biped(name="biped", scale=1.0):
    names = ["hips", "spine", "chest", "neck", "head", "arm.L", "fore.L", "hand.L",
             "arm.R", "fore.R", "hand.R", "leg.L", "shin.L", "leg.R", "shin.R"]
    parents = [-1, 0, 1, 2, 3, 2, 5, 6, 2, 8, 9, 0, 11, 0, 13]
    P = np.array([[0, 1, 0], [0, 1.2, 0], [0, 1.4, 0], [0, 1.6, 0], [0, 1.75, 0],
                  [0.2, 1.45, 0], [0.45, 1.45, 0], [0.7, 1.45, 0],
                  [-0.2, 1.45, 0], [-0.45, 1.45, 0], [-0.7, 1.45, 0],
                  [0.1, 0.95, 0], [0.1, 0.5, 0], [-0.1, 0.95, 0], [-0.1, 0.5, 0]]) * scale
    return toy(names, parents, P, name, tri=0.05 * scale)  # the surface scales with the skeleton


def plan_for(chars, actions, **characters):
    cfg = Config(characters={cid: {"path": f"{cid}.glb", **characters.get(cid, {})} for cid in chars},
                 actions=actions)
    return plan_operations(chars, cfg)


@pytest.fixture(scope="module")
def real():
    """The shared characters used here, loaded once."""
    names = {"CesiumMan", "RiggedFigure", "Fox", "Horse", "Knight", "Velociraptor"}
    return {n: load_character(asset(n)) for n in names}


def plan_config(name, real):
    cfg = load_config(CONFIGS / name)
    by_file = {Path(v.path).name: k for k, v in cfg.characters.items()}
    files = {"CesiumMan.glb": "CesiumMan", "RiggedFigure.glb": "RiggedFigure", "Fox.glb": "Fox",
             "Horse.glb": "Horse", "KnightCharacter.glb": "Knight", "Velociraptor.glb": "Velociraptor"}
    inputs = {cid: real[files[Path(c.path).name]] for cid, c in cfg.characters.items()}
    assert by_file
    return plan_operations(inputs, cfg)


def assert_valid_skeleton(sk):
    assert len(set(sk.names)) == sk.num_joints
    assert np.all(sk.parents < np.arange(sk.num_joints))
    W = sk.rest_worlds()
    assert np.allclose(W @ sk.inverse_binds, np.eye(4), atol=1e-8)


# --------------------------------------------------------------------------------------------
# The harmonic translation field
# --------------------------------------------------------------------------------------------


def jacobi(parents, fixed, values, iterations=20000):
    """Slow reference: iterate t_i <- mean of neighbours on the free joints."""
    A = skeleton_adjacency(parents).toarray()
    t = np.zeros((len(A), 3))
    t[fixed] = values
    free = np.ones(len(A), bool)
    free[fixed] = False
    deg = A.sum(1)
    for _ in range(iterations):
        t[free] = (A @ t)[free] / deg[free, None]
    return t[: len(parents)]


def test_one_fixed_joint_is_rigid():
    parents = [-1, 0, 1, 1, 3, -1, 5]  # a forest: two trees
    t = smooth_translations(parents, [4], [[1.0, -2.0, 0.5]])
    assert np.allclose(t, [1.0, -2.0, 0.5])
    assert np.allclose(smooth_translations(parents, [], np.zeros((0, 3))), 0)


def test_two_fixed_joints_give_a_harmonic_field():
    rng = np.random.default_rng(0)
    parents = np.array([-1, 0, 1, 2, 3, 2, 5, 6, 0, 8, 9])
    fixed = np.array([4, 7])
    values = rng.normal(size=(2, 3))
    t = smooth_translations(parents, fixed, values)
    assert np.allclose(t[fixed], values)
    A = skeleton_adjacency(parents).toarray()[:-1, :-1]
    for i in set(range(len(parents))) - set(fixed):
        nb = np.flatnonzero(A[i])
        assert np.allclose(t[i], t[nb].mean(axis=0)), i  # the Laplacian property
    assert np.allclose(t, jacobi(parents, fixed, values), atol=1e-6)
    assert not np.allclose(t, t[0])  # not rigid


# --------------------------------------------------------------------------------------------
# Output skeleton and provenance (synthetic)
# --------------------------------------------------------------------------------------------


def test_self_composition_is_identity_synthetic():
    b = biped()
    for chars, actions in [
        ({"x": b}, [{"op": "replace", "source": "x", "source_joint": "arm.L", "target": "x", "target_joint": "arm.L"}]),
        ({"x": b, "y": b}, [{"op": "replace", "source": "y", "source_joint": "arm.L", "target": "x",
                             "target_joint": "arm.L"}]),
    ]:
        plan = plan_for(chars, actions)
        sk = plan.skeleton
        assert sk.names == b.skeleton.names
        assert np.array_equal(sk.parents, b.skeleton.parents)
        for f in ("translations", "rotations", "scales"):
            assert np.allclose(getattr(sk, f), getattr(b.skeleton, f), atol=1e-12)
        assert len(plan.fused_pairs) == 1 and sk.names[plan.fused_pairs[0].output] == "arm.L"


def test_attach_names_provenance_and_order():
    x, y = biped("x"), biped("y")
    plan = plan_for({"x": x, "y": y}, [
        {"op": "attach", "source": "y", "source_joint": "chest", "target": "x", "target_joint": "hips"}])
    sk = plan.skeleton
    assert_valid_skeleton(sk)
    # x whole + y's chest subtree minus the fused chest
    n_chest = int(y.skeleton.subtree(2).sum())
    assert sk.num_joints == 15 + n_chest - 1
    assert plan.used["x"].all() and plan.used["y"].sum() == n_chest
    # collisions: the body keeps the name, a grafted joint gets its character id as prefix
    # (readable in Blender and engines, where ``.001`` reads as a duplicate)
    assert "neck" in sk.names and "y_neck" in sk.names and "y_chest" not in sk.names
    assert not any(n.endswith(".001") for n in sk.names)
    assert plan.report["renamed"]["y_neck"] == "y:neck"
    hips = sk.names.index("hips")
    assert plan.provenance[hips] == (("x", 0), ("y", 2))
    for o, prov in enumerate(plan.provenance):
        for cid, j in prov:
            assert plan.image[cid][j] == o
    # y moved rigidly onto x's hips: its chest lands exactly there
    Wy = plan.positioned["y"].skeleton.rest_worlds()
    Wx = plan.positioned["x"].skeleton.rest_worlds()
    assert np.allclose(Wy[2, :3, 3], Wx[0, :3, 3])
    # grafted joints keep their positioned world transform in the output
    Wr = sk.rest_worlds()
    assert np.allclose(Wr[sk.names.index("y_neck")], Wy[3])


def test_replace_drops_the_target_subtree():
    x, y = biped("x"), biped("y", scale=2.0)
    plan = plan_for({"x": x, "y": y}, [
        {"op": "replace", "source": "y", "source_joint": "arm.L", "target": "x", "target_joint": "arm.L"},
        {"op": "remove", "target": "x", "target_joint": "leg.R"}])
    sk = plan.skeleton
    assert_valid_skeleton(sk)
    used = dict(zip(x.skeleton.names, plan.used["x"]))
    assert used["arm.L"] and not used["fore.L"] and not used["hand.L"]
    assert not used["leg.R"] and not used["shin.R"] and used["leg.L"]
    assert plan.scales["y"] == pytest.approx(0.5)  # limb-length ratio
    assert plan.report["characters"]["y"]["scale_method"] == "limb-length"
    # the override wins
    plan2 = plan_for({"x": x, "y": y}, [
        {"op": "replace", "source": "y", "source_joint": "arm.L", "target": "x", "target_joint": "arm.L"}],
        y={"scale": 0.25})
    assert plan2.scales["y"] == 0.25 and plan2.report["characters"]["y"]["scale_method"] == "override"


def test_two_fused_pairs_move_the_source_smoothly():
    x, y = biped("x"), biped("y")
    shifted = toy(y.skeleton.names, y.skeleton.parents,
                  y.skeleton.rest_worlds()[:, :3, 3] * [1.3, 1, 1] + [0, 0, 0.4], "y")
    plan = plan_for({"x": x, "y": shifted}, [
        {"op": "replace", "source": "y", "source_joint": "arm.L", "target": "x", "target_joint": "arm.L"},
        {"op": "replace", "source": "y", "source_joint": "arm.R", "target": "x", "target_joint": "arm.R"}],
        y={"scale": 1.0})
    t = plan.translations["y"]
    Px = x.skeleton.rest_worlds()[:, :3, 3]
    Py = shifted.skeleton.rest_worlds()[:, :3, 3]
    assert np.allclose(Py[5] + t[5], Px[5]) and np.allclose(Py[8] + t[8], Px[8])
    assert not np.allclose(t[5], t[8])
    A = skeleton_adjacency(shifted.skeleton.parents).toarray()[:-1, :-1]
    for i in set(range(15)) - {5, 8}:
        assert np.allclose(t[i], t[np.flatnonzero(A[i])].mean(axis=0))
    # the mesh follows by skinning: each vertex moves by its joint's translation
    V0, W = rest_world_mesh(shifted)
    V1, _ = rest_world_mesh(plan.positioned["y"])
    assert np.allclose(V1, V0 + W @ t)


def test_structural_errors():
    b = biped()
    with pytest.raises(InputError, match="grafted onto itself"):
        plan_for({"x": b}, [{"op": "attach", "source": "x", "source_joint": "arm.L", "target": "x",
                             "target_joint": "hand.L"}])
    with pytest.raises(InputError, match="twice"):
        plan_for({"x": b}, [{"op": "attach", "source": "x", "source_joint": "arm.L", "target": "x",
                             "target_joint": "head"}])
    with pytest.raises(InputError, match=r"actions\[1\].target_joint.*removed"):
        plan_for({"x": b, "y": b}, [
            {"op": "remove", "target": "x", "target_joint": "arm.L"},
            {"op": "attach", "source": "y", "source_joint": "head", "target": "x", "target_joint": "hand.L"}])
    with pytest.raises(InputError, match="cycle"):
        plan_for({"x": b, "y": b}, [
            {"op": "attach", "source": "y", "source_joint": "hips", "target": "x", "target_joint": "hand.L"},
            {"op": "attach", "source": "x", "source_joint": "hips", "target": "y", "target_joint": "hand.R"}])
    with pytest.raises(InputError, match=r"no joint 'arm\.l'.*closest: arm\.L"):
        plan_for({"x": b}, [{"op": "remove", "target": "x", "target_joint": "arm.l"}])
    with pytest.raises(InputError, match=r"characters\.x\.rotations.*closest: neck"):
        plan_for({"x": b}, [], x={"rotations": {"nek": [0, 0, 10]}})


def test_user_rotation_poses_the_subtree():
    b = biped()
    plan = plan_for({"x": b}, [], x={"rotations": {"arm.L": [0, 0, -90]}})
    P0 = b.skeleton.rest_worlds()[:, :3, 3]
    P1 = plan.skeleton.rest_worlds()[:, :3, 3]
    sub = b.skeleton.subtree(5)
    assert np.allclose(P1[~sub], P0[~sub])
    assert np.allclose(P1[7], P0[5] + [0, -0.5, 0])  # the arm now hangs down
    V1, W = rest_world_mesh(plan.positioned["x"])
    V0, _ = rest_world_mesh(b)
    R = quat_to_matrix(plan.positioned["x"].skeleton.rotations[5])
    moved = part_weights(W, sub) > 0.5
    assert np.allclose(V1[moved], (V0[moved] - P0[5]) @ R.T + P0[5])
    assert np.allclose(V1[~moved], V0[~moved])


# --------------------------------------------------------------------------------------------
# position_character on real characters: rebasing, scale, placement, clips
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["CesiumMan", "Horse", "Fox"])
def test_positioning_scales_rest_and_animation(real, name):
    ch = real[name]
    s = 0.37
    R = quat_to_matrix(np.array([0.0, np.sin(0.3), 0.0, np.cos(0.3)]))
    G = np.eye(4)
    G[:3, :3] = R
    G[:3, 3] = [1.0, -2.0, 0.5]
    pos = position_character(ch, scale=s, placement=G)
    assert np.allclose(pos.skeleton.rest_worlds() @ pos.skeleton.inverse_binds, np.eye(4), atol=1e-8)
    for before, after in zip(rest_pose(ch), rest_pose(pos)):
        assert np.allclose(after, (s * before) @ R.T + G[:3, 3], atol=1e-6 * s * np.ptp(before))
    clip = ch.clips[0]
    times = np.linspace(clip.start, clip.end, 5)
    M0 = skinning_matrices(ch.skeleton, *sample_clip(ch.skeleton, clip, times))
    M1 = skinning_matrices(pos.skeleton, *sample_clip(pos.skeleton, pos.clips[0], times))
    for m0, m1 in zip(ch.meshes, pos.meshes):
        U0 = linear_blend_skinning(m0.positions, m0.joints, m0.weights, M0)
        U1 = linear_blend_skinning(m1.positions, m1.joints, m1.weights, M1)
        # exact up to the asset's own bind/rest mismatch (see position_character's notes)
        assert np.allclose(U1, (s * U0) @ R.T + G[:3, 3], atol=3e-4 * s * np.ptp(U0))


# --------------------------------------------------------------------------------------------
# Real configs
# --------------------------------------------------------------------------------------------


def test_self_composition_real(real):
    plan = plan_config("self_composition.toml", real)
    cm = real["CesiumMan"].skeleton
    sk = plan.skeleton
    assert sk.names == cm.names
    assert np.array_equal(sk.parents, cm.parents)
    assert np.allclose(sk.translations, cm.translations, atol=1e-12)
    assert np.allclose(sk.rotations, cm.rotations, atol=1e-12)
    assert np.allclose(sk.scales, cm.scales, atol=1e-12)
    assert np.allclose(sk.rest_worlds(), cm.rest_worlds(), atol=1e-9)
    assert [a.name for a in sk.anchors] == [a.name for a in cm.anchors]
    assert plan.scales == {"body": 1.0, "donor": 1.0}
    body = plan.positioned["body"]
    assert np.array_equal(body.skeleton.rotations, cm.rotations)
    for a, b in zip(rest_pose(real["CesiumMan"]), rest_pose(body)):
        assert np.allclose(a, b, atol=1e-9)


def test_centaur_real(real):
    plan = plan_config("centaur.toml", real)
    sk = plan.skeleton
    assert_valid_skeleton(sk)
    horse, knight = real["Horse"].skeleton, real["Knight"].skeleton
    fused = plan.fused_pairs[0]
    assert sk.names[fused.output] == "Neck1"
    assert plan.provenance[fused.output] == (("horse", horse.index("Neck1")), ("knight", knight.index("Abdomen")))
    used_h = dict(zip(horse.names, plan.used["horse"]))
    assert used_h["Neck1"] and not used_h["Neck2"] and not used_h["Head"] and used_h["IKBackLeg.L"]
    assert plan.used["knight"].sum() == knight.subtree(knight.index("Abdomen")).sum()
    assert len(sk.roots) == 5  # the Horse's five roots survive
    # the knight's torso sits on the horse's neck base, at a matched scale
    Wr = sk.rest_worlds()
    assert np.allclose(plan.positioned["knight"].skeleton.rest_worlds()[knight.index("Abdomen"), :3, 3],
                       Wr[fused.output, :3, 3])
    assert "knight_Torso" in sk.names  # the knight's Torso after the horse's
    # a torso is no limb: its scale fills the ring where the horse's neck leaves the body, whatever
    # the chains (the horse's neck and head against the knight's spine and arm, about half of it)
    assert limb_kind(real["Knight"], knight.index("Abdomen")) is None
    assert plan.report["characters"]["knight"]["scale_method"] == "cross-section"

    def cut(c, j):
        c = rebase(c)
        V, W = rest_world_mesh(c)
        return cut_section(V, rest_world_faces(c), W, c.skeleton.subtree(j))

    ratio = cut(real["Horse"], horse.index("Neck1")) / cut(real["Knight"], knight.index("Abdomen"))
    assert plan.scales["knight"] == pytest.approx(ratio, rel=1e-9)
    Ph, Pk = horse.rest_worlds()[:, :3, 3], knight.rest_worlds()[:, :3, 3]
    chain = (chain_length(horse.parents, Ph, horse.index("Neck1"))
             / chain_length(knight.parents, Pk, knight.index("Abdomen")))
    assert 1.5 < ratio / chain <= AGREEMENT


def _limb(sk, names):
    P = sk.rest_worlds()[:, :3, 3]
    idx = [sk.index(n) for n in names]
    return float(sum(np.linalg.norm(P[b] - P[a]) for a, b in zip(idx, idx[1:])))


def test_fox_scale_matches_limb_lengths(real):
    plan = plan_config("fox_arm.toml", real)
    arm = _limb(real["CesiumMan"].skeleton, ["Skeleton_arm_joint_L__4_", "Skeleton_arm_joint_L__3_",
                                             "Skeleton_arm_joint_L__2_"])
    leg = _limb(real["Fox"].skeleton, ["b_LeftUpperArm_09", "b_LeftForeArm_010", "b_LeftHand_011"])
    ratio = arm / leg
    assert 0.75 * ratio <= plan.scales["fox"] <= 1.25 * ratio
    assert 0.005 < plan.scales["fox"] < 0.03  # ~79 units tall -> about a metre
    # one fused pair: a rigid translation of the whole (scaled) fox
    t = plan.translations["fox"]
    assert np.allclose(t, t[0])
    V0, _ = rest_world_mesh(position_character(real["Fox"], scale=plan.scales["fox"]))
    V1, _ = rest_world_mesh(plan.positioned["fox"])
    assert np.allclose(V1, V0 + t[0], atol=1e-9)
    # the override wins
    cfg = load_config(CONFIGS / "fox_arm.toml")
    chars = dict(cfg.characters)
    chars["fox"] = chars["fox"].model_copy(update={"scale": 0.02})
    cfg2 = cfg.model_copy(update={"characters": chars})
    plan2 = plan_operations({"man": real["CesiumMan"], "fox": real["Fox"]}, cfg2)
    assert plan2.scales["fox"] == 0.02
    assert plan2.report["characters"]["fox"]["scale_method"] == "override"


def test_limb_swap_two_pairs_real(real):
    plan = plan_config("limb_swap.toml", real)
    assert_valid_skeleton(plan.skeleton)
    rf = real["RiggedFigure"].skeleton
    t = plan.translations["figure"]
    fixed = [rf.index("arm_joint_L_1"), rf.index("leg_joint_R_1")]
    A = skeleton_adjacency(rf.parents).toarray()[:-1, :-1]
    for i in set(range(rf.num_joints)) - set(fixed):
        assert np.allclose(t[i], t[np.flatnonzero(A[i])].mean(axis=0), atol=1e-12)
    out = plan.skeleton.rest_worlds()[:, :3, 3]
    pos = plan.positioned["figure"].skeleton.rest_worlds()[:, :3, 3]
    for f in plan.fused_pairs:
        assert np.allclose(pos[f.source_joint], out[f.output])


@pytest.mark.parametrize("name", ["tail_graft.toml", "three_characters.toml", "limb_swap.toml"])
def test_real_configs_give_valid_skeletons(real, name):
    plan = plan_config(name, real)
    assert_valid_skeleton(plan.skeleton)
    for cid, ch in plan.positioned.items():  # every positioned input is rebased: bind = rest
        W = ch.skeleton.rest_worlds()
        assert np.allclose(W @ ch.skeleton.inverse_binds, np.eye(4), atol=1e-8)
        V, _ = rest_world_mesh(ch)
        assert np.allclose(V, np.concatenate([m.positions for m in ch.meshes]), atol=1e-9)
    for cid, used in plan.used.items():
        assert np.array_equal(plan.image[cid] >= 0, used)
    counts = np.zeros(plan.skeleton.num_joints, int)
    for prov in plan.provenance:
        assert prov
    for cid, im in plan.image.items():
        np.add.at(counts, im[im >= 0], 1)
    assert np.all(counts >= 1)
    assert sum(len(p) - 1 for p in plan.provenance) == len(
        [f for f in plan.fused_pairs if f.source != f.target or f.source_joint != f.target_joint])


@pytest.mark.parametrize("name", ["knight_arm.toml", "centaur.toml", "three_characters.toml"])
def test_output_skeleton_has_unit_scale(real, name):
    """Issue 25: the Quaternius armatures' x100 (and the composed scale) are baked into S_R's rest
    translations; every joint and anchor keeps its rest place and orientation with world scale 1."""
    plan = plan_config(name, real)
    sk = plan.skeleton
    W = sk.rest_worlds()
    assert np.abs(np.linalg.norm(W[:, :3, :3], axis=1) - 1).max() <= 1e-6
    assert np.abs(np.linalg.norm(sk.anchor_worlds()[:, :3, :3], axis=1) - 1).max(initial=0) <= 1e-6
    assert_valid_skeleton(sk)
    scaled = False
    for o, ((cid, j), *_) in enumerate(plan.provenance):  # the primary member's rest frame
        src = plan.positioned[cid].skeleton.rest_worlds()[j]
        s = np.linalg.norm(src[:3, :3], axis=0)
        scaled |= bool(np.abs(s - 1).max() > 1e-3)
        np.testing.assert_allclose(W[o, :3, 3], src[:3, 3], atol=1e-9 * max(1.0, np.abs(src[:3, 3]).max()))
        np.testing.assert_allclose(W[o, :3, :3], src[:3, :3] / s, atol=1e-5)  # float32 shear
    assert scaled  # the config mixes scaled frames in: the test sees what it is about


# --------------------------------------------------------------------------------------------
# The compose entry point
# --------------------------------------------------------------------------------------------


def test_compose_from_a_file_reports_and_progresses():
    import rigmix
    from rigmix.pipeline import mapping_table

    asset("CesiumMan"), asset("RiggedFigure")
    seen = []
    comp = rigmix.compose(CONFIGS / "limb_swap.toml", progress=lambda s, k, n: seen.append((s, k)),
                          until="mapping")
    # the running stage is named as it starts (fusion takes minutes on a large junction)
    assert seen == [("load", 0), ("operations", 1), ("mapping", 2), ("done", 3)]
    # and so are the fusion's and the weights' sub-steps, with the stage's index
    seen.clear()
    rigmix.compose(CONFIGS / "limb_swap.toml", progress=lambda s, k, n: seen.append((s, k)), until="weights")
    fusion = [s for s, k in seen if s.startswith("fusion: ") and k == 3]
    weights = [s for s, k in seen if s.startswith("weights: ") and k == 4]
    assert fusion[:2] == ["fusion: presence", "fusion: seams"] and "fusion: junction 1 of 1" in fusion
    assert fusion[-1] == "fusion: assembly" and weights[0] == "weights: retarget" and weights[-1] == "weights: weld"
    assert [s for s, _ in seen if ":" not in s] == ["load", "operations", "mapping", "fusion", "weights", "done"]
    assert seen.index(("fusion", 3)) < seen.index(("fusion: presence", 3)) < seen.index(("weights", 4))
    assert comp.skeleton is comp.plan.skeleton
    assert set(comp.maps) == {"cesium", "figure"}
    rep = comp.report
    assert rep["name"] == "limb_swap" and rep["operations"]["characters"]["figure"]["scale_method"] == "limb-length"
    assert set(rep["timings"]) >= {"load", "operations", "mapping"}
    rows = mapping_table(comp)
    assert len(rows) == 19 + 19 and all(0 <= r["confidence"] <= 1 for r in rows)
    # a file listed twice is read once
    comp2 = rigmix.compose(CONFIGS / "self_composition.toml", until="mapping")
    assert comp2.inputs["body"] is comp2.inputs["donor"]


def test_compose_builtin_config_in_code():
    import rigmix
    from rigmix.pipeline import load_characters

    cfg = rigmix.Config(characters={"body": {"path": "builtin:humanoid"}, "donor": {"path": "builtin:humanoid"}},
                        actions=[{"op": "replace", "source": "donor", "source_joint": "UpperArm.L",
                                  "target": "body", "target_joint": "UpperArm.L"}])
    comp = rigmix.compose(cfg, until="mapping")
    h = comp.inputs["body"].skeleton
    assert comp.skeleton.names == h.names and np.array_equal(comp.skeleton.parents, h.parents)
    assert np.allclose(comp.skeleton.translations, h.translations)
    for bm in comp.maps.values():
        assert np.array_equal(bm.target, np.arange(h.num_joints)) and np.allclose(bm.confidence, 1)
    bad = rigmix.Config(characters={"a": {"path": "builtin:dragon"}})
    with pytest.raises(InputError, match="no built-in character 'dragon'.*humanoid"):
        load_characters(bad)


def test_plan_dicts_follow_the_config_order():
    x, y = biped("x"), biped("y")
    plan = plan_for({"y": y, "x": x}, [  # the source listed first: positioned after its target
        {"op": "attach", "source": "y", "source_joint": "head", "target": "x", "target_joint": "hand.L"}])
    for d in (plan.positioned, plan.scales, plan.translations, plan.used, plan.image,
              plan.report["characters"]):
        assert list(d) == ["y", "x"]



def test_compose_until_rejects_unknown_stages():
    from rigmix import pipeline

    cfg = Config(characters={"x": {"path": "x.glb"}})
    with pytest.raises(ValueError, match="unknown stage"):
        pipeline.compose(cfg, until="render")


@pytest.mark.parametrize("target, target_joint, source, source_joint, kind, method", [
    # a neck's chain runs up into the skull: CesiumMan's is twice the Bull's for the same neck
    (("corpus", "Bull"), "Neck1", ("asset", "CesiumMan"), "Skeleton_neck_joint_1", "head", "cross-section"),
    # an arm's chain is its length: the Platformer's is 2.1 times the Adventurer's cut ratio
    (("corpus", "Adventurer"), "UpperArm.L", ("corpus", "PlatformerCharacter"), "UpperArm.L", "arm",
     "limb-length"),
])
def test_replace_scale_takes_the_chain_only_along_a_limb(target, target_joint, source, source_joint, kind,
                                                        method):
    """Where the chain ratio and the cut's ratio differ but agree within AGREEMENT, a head takes
    the cut's (it fills the neck's hole) and an arm the chain's."""
    def load(where, name):
        return rebase(load_character(corpus(name) if where == "corpus" else asset(name)))

    t, s = load(*target), load(*source)
    jt, js = t.skeleton.names.index(target_joint), s.skeleton.names.index(source_joint)
    assert limb_kind(t, jt) == kind and limb_kind(s, js) == kind

    def chain(c, j):
        return chain_length(c.skeleton.parents, c.skeleton.rest_worlds()[:, :3, 3], j)

    def cut(c, j):
        V, W = rest_world_mesh(c)
        return cut_section(V, rest_world_faces(c), W, c.skeleton.subtree(j))

    chain, cut = chain(t, jt) / chain(s, js), cut(t, jt) / cut(s, js)
    assert 1.3 < max(chain / cut, cut / chain) <= AGREEMENT  # they differ, within the agreement
    scale, how = pair_scale("replace", t, jt, s, js)
    assert how == method
    assert scale == pytest.approx(cut if method == "cross-section" else chain, rel=1e-12)


# --------------------------------------------------------------------------------------------
# Facing: a source modelled facing another way is turned to face the way its target faces
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("source, target", [((1, 0, 0), (0, 0, 1)), ((0, 0, 1), (1, 0, 0)),
                                            ((0, 0, 1), (0, 0, -1)), ((-1, 0, 0), (0, 0, 1)),
                                            ((0.6, 0, 0.8), (0.6, 0, 0.8))])
def test_facing_turn_maps_forward_onto_forward(source, target):
    R = facing_turn(source, target)
    assert np.allclose(R @ np.asarray(source, float), target, atol=1e-12)
    assert np.allclose(R @ [0, 1, 0], [0, 1, 0])  # about +Y: up stays up
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)


def test_facing_turn_of_a_vertical_direction_is_none():
    assert np.array_equal(facing_turn((0, 1, 0), (0, 0, 1)), np.eye(3))


@pytest.fixture(scope="module")
def wasp_wings_on_cesiumman(tmp_path_factory):
    """The corpus matrix's wings case: the Wasp (modelled facing +X) gives both wings, attached at
    CesiumMan's (facing +Z) upper spine joint."""
    cfg = load_config(corpus_case("wings__CesiumMan__Wasp", tmp_path_factory.mktemp("wings")))
    inputs = load_characters(cfg)
    return cfg, inputs, plan_operations(inputs, cfg)


def test_a_source_facing_another_way_is_turned_to_face_its_target(wasp_wings_on_cesiumman):
    cfg, inputs, plan = wasp_wings_on_cesiumman
    body = plan.positioned["body"]
    wasp = plan.positioned["donor"]
    assert classify_limbs(inputs["donor"]).forward == (1.0, 0.0, 0.0)
    assert classify_limbs(body).forward == (0.0, 0.0, 1.0)
    # the positioned wasp faces the body's way: its head lies ahead (+Z) of its wings
    sk = wasp.skeleton
    P = sk.rest_worlds()[:, :3, 3]
    head, wl, wr = sk.index("Head"), sk.index("Wing.L"), sk.index("Wing.R")
    assert P[head, 2] - P[[wl, wr], 2].mean() > 0.5 * abs(P[head, 0] - P[[wl, wr], 0].mean())
    assert plan.report["characters"]["donor"]["facing_turn_degrees"] == pytest.approx(-90.0)
    # the wing on the wasp's left spreads to the body's left: +X for a character facing +Z
    V, W = rest_world_mesh(wasp)
    W = dense_rows(W)
    assert V[W[:, wl] > 0.5, 0].mean() > P[wl, 0] > V[W[:, wr] > 0.5, 0].mean()


def test_turning_to_face_can_be_turned_off(tmp_path):
    path = corpus_case("wings__CesiumMan__Wasp", tmp_path)
    path.write_text(path.read_text() + "\n[positioning]\nface = false\n")
    cfg = load_config(path)
    plan = plan_operations(load_characters(cfg), cfg)
    assert plan.report["characters"]["donor"]["facing_turn_degrees"] == 0.0
    sk = plan.positioned["donor"].skeleton
    P = sk.rest_worlds()[:, :3, 3]
    assert P[sk.index("Head"), 0] - P[sk.index("Wing.L"), 0] > 0  # still facing +X


def test_no_half_turn_between_rigs_mirrored_on_the_same_plane(tmp_path):
    """The Cyberpunk character's facing vote tips to -Z in its bind pose (the pose compositions use)
    while CesiumMan faces +Z: turned by half, its arm went on CesiumMan backwards (0.75 of it
    showing). Both are mirrored across X: neither is turned."""
    cfg = load_config(corpus_case("arm_swap__CesiumMan__CyberpunkCharacter", tmp_path))
    inputs = load_characters(cfg)
    plan = plan_operations(inputs, cfg)
    assert plan.report["characters"]["donor"]["facing_turn_degrees"] == 0.0
    sk = plan.positioned["donor"].skeleton
    P0 = rebase(inputs["donor"]).skeleton.rest_worlds()[:, :3, 3]
    P = sk.rest_worlds()[:, :3, 3]
    arm = sk.index(cfg.actions[0].source_joint)
    # the positioned arm is the file's arm scaled and moved, not turned: its bones point the same way
    d0, d = P0[sk.subtree(arm)] - P0[arm], P[sk.subtree(arm)] - P[arm]
    assert np.allclose(d, plan.scales["donor"] * d0, atol=1e-6 * np.abs(d).max())


def fused_wings(path):
    """The matrix's wings case written as the paper's attach: each wing root fused with the target
    joint (no ``keep_joint``)."""
    text = path.read_text()
    assert "keep_joint = true" in text
    path.write_text(text.replace("keep_joint = true\n", ""))
    return path


def test_parts_fused_to_one_joint_are_warned_of(tmp_path, caplog):
    """Both Wasp wings attached at CesiumMan's one spine joint become that joint (fused pairs
    become one joint): the output has no wing bone, and the user is told so, with the fix."""
    import logging

    cfg = load_config(fused_wings(corpus_case("wings__CesiumMan__Wasp", tmp_path)))
    inputs = load_characters(cfg)
    with caplog.at_level(logging.WARNING, logger="rigmix.operations.plan"):
        plan = plan_operations(inputs, cfg)
    (msg,) = [r.getMessage() for r in caplog.records if "become that one joint" in r.getMessage()]
    assert "'Wing.L'" in msg and "'Wing.R'" in msg and cfg.actions[0].target_joint in msg
    assert "attach each at a joint of its own" in msg and "keep_joint" in msg
    assert not any("Wing" in n for n in plan.skeleton.names)  # what the warning is about

    caplog.clear()
    cfg = load_config(corpus_case("arm_swap__CesiumMan__CyberpunkCharacter", tmp_path))
    with caplog.at_level(logging.WARNING, logger="rigmix.operations.plan"):
        plan_operations(load_characters(cfg), cfg)
    assert not [r for r in caplog.records if "become that one joint" in r.getMessage()]


def test_kept_joints_hang_from_their_target_with_their_spacing(wasp_wings_on_cesiumman):
    """``keep_joint``: each Wasp wing root stays a joint of its own, a child of CesiumMan's spine
    joint. The two keep their directions from it (the Wasp moves so that their mean lands on it),
    and at least their spacing: spread out to CesiumMan's surface, where the spine is wider than
    the Wasp's thorax."""
    import igl

    cfg, inputs, plan = wasp_wings_on_cesiumman
    sk = plan.skeleton
    target = cfg.actions[0].target_joint
    assert all(a.keep_joint for a in cfg.actions)
    assert plan.fused_pairs == () and len(plan.attached_pairs) == 2
    assert plan.junction_pairs == plan.attached_pairs
    donor = inputs["donor"].skeleton
    for pair, name in zip(plan.attached_pairs, ("Wing.L", "Wing.R")):
        assert sk.names[pair.output] == name and sk.names[sk.parents[pair.output]] == target
        assert plan.provenance[pair.output] == (("donor", donor.index(name)),)
    assert [e["parent"] for e in plan.report["attached_joints"]] == [target, target]
    assert_valid_skeleton(sk)
    P = sk.rest_worlds()[:, :3, 3]
    wl, wr, t = sk.index("Wing.L"), sk.index("Wing.R"), sk.index(target)
    # the Wasp as turned and scaled, unspread: its wing roots about their mean
    turn = plan.transforms["donor"][:3, :3]
    P0 = rebase(inputs["donor"]).skeleton.rest_worlds()[:, :3, 3] @ turn.T
    roots = P0[[donor.index("Wing.L"), donor.index("Wing.R")]]
    offsets = roots - roots.mean(axis=0)
    for o, k in zip(offsets, (wl, wr)):
        d = P[k] - P[t]
        assert np.allclose(d / np.linalg.norm(d), o / np.linalg.norm(o), atol=1e-9)
        assert np.linalg.norm(d) >= np.linalg.norm(o) * (1 - 1e-9)
    body = plan.positioned["body"]
    V, _ = rest_world_mesh(body)
    w = igl.fast_winding_number(V, rest_world_faces(body), P[[wl, wr]])
    assert np.all(w < 0.5)  # on CesiumMan's surface, not inside him
    assert plan.scales["donor"] > 0


def test_spread_to_surface_lengthens_only_the_offsets_that_end_inside():
    """A unit sphere about its centre: an offset of 0.3 ends inside and is lengthened to the
    surface (within one ray step); one of 1.5 ends outside and stays; a zero offset stays zero."""
    from fusion_shapes import sphere

    V, F = sphere(3)
    offsets = np.array([[0.3, 0.0, 0.0], [0.0, -1.5, 0.0], [0.0, 0.0, 0.0], [0.0, 0.2, 0.2]])
    out = spread_to_surface(V, F, np.zeros(3), offsets)
    step = np.linalg.norm(np.ptp(V, axis=0)) / SPREAD_STEPS
    r = np.linalg.norm(out, axis=1)
    assert 1.0 - 0.02 <= r[0] <= 1.0 + step and 1.0 - 0.02 <= r[3] <= 1.0 + step
    assert np.array_equal(out[1], offsets[1]) and np.array_equal(out[2], offsets[2])
    unit = offsets[[0, 3]] / np.linalg.norm(offsets[[0, 3]], axis=1)[:, None]
    assert np.allclose(out[[0, 3]] / r[[0, 3], None], unit)
    # from a centre outside the body, nothing is lengthened
    assert np.array_equal(spread_to_surface(V, F, np.array([3.0, 0, 0]), offsets), offsets)


def test_a_kept_joint_is_not_warned_of(tmp_path, caplog):
    import logging

    cfg = load_config(corpus_case("wings__CesiumMan__Wasp", tmp_path))
    with caplog.at_level(logging.WARNING, logger="rigmix.operations.plan"):
        plan_operations(load_characters(cfg), cfg)
    assert not [r for r in caplog.records if "become that one joint" in r.getMessage()]


def test_keep_joint_is_an_attach_option_only(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('[characters.x]\npath = "x.glb"\n[characters.y]\npath = "y.glb"\n'
                    '[[actions]]\nop = "replace"\nsource = "y"\nsource_joint = "arm.L"\ntarget = "x"\n'
                    'target_joint = "arm.L"\nkeep_joint = true\n')
    with pytest.raises(InputError, match=r"bad\.toml: actions.*keep_joint"):
        load_config(path)


def test_a_kept_joint_attached_onto_a_body_keeps_its_local_bone():
    """A toy arm attached at the hips with ``keep_joint``: the arm root is a new child of the hips
    at the same rest world transform, and its own children still hang from it."""
    x, y = biped("x"), biped("y")
    plan = plan_for({"x": x, "y": y}, [
        {"op": "attach", "source": "y", "source_joint": "arm.L", "target": "x", "target_joint": "hips",
         "keep_joint": True}], y={"scale": 1.0})
    sk = plan.skeleton
    assert_valid_skeleton(sk)
    assert sk.num_joints == 15 + 3
    arm = plan.output_index("y", 5)
    assert sk.parents[arm] == plan.output_index("x", 0)
    assert sk.parents[plan.output_index("y", 6)] == arm
    W = sk.rest_worlds()
    assert np.allclose(W[arm, :3, 3], W[plan.output_index("x", 0), :3, 3])  # one kept joint: lands on it
    assert np.allclose(W[plan.output_index("y", 6)], plan.positioned["y"].skeleton.rest_worlds()[6])


def test_a_detached_foot_moves_with_its_leg(tmp_path):
    """Leela's left leg on EnemyLarge (the corpus matrix's leg swap): her IK foot (``Foot.L``, a
    root joint carrying the foot's skin, fused with EnemyLarge's ``Foot.L``) moves as her leg's
    root does, and the fused joint rests where her foot is: at the end of her leg, not at
    EnemyLarge's foot, a tenth of the output's size away."""
    cfg = load_config(corpus_case("leg_swap__EnemyLarge__Leela", tmp_path))
    inputs = load_characters(cfg)
    plan = plan_operations(inputs, cfg)
    assert plan.report["characters"]["donor"]["moved_with_limb"] == ["Foot.L"]
    donor = inputs["donor"].skeleton
    t = plan.translations["donor"]
    assert np.allclose(t[donor.index("Foot.L")], t[donor.index("UpperLeg.L")])
    sk = plan.skeleton
    P = sk.rest_worlds()[:, :3, 3]
    size = np.linalg.norm(np.ptp(P, axis=0))
    foot, heel = sk.index("Foot.L"), sk.index("FootBack.L")
    assert np.linalg.norm(P[foot] - P[heel]) < 1e-6 * size  # in Leela's file the foot sits at the heel
    Pd = plan.positioned["donor"].skeleton.rest_worlds()[:, :3, 3]
    assert np.allclose(P[foot], Pd[donor.index("Foot.L")])
    Pb = plan.positioned["body"].skeleton.rest_worlds()[:, :3, 3]
    assert np.linalg.norm(P[foot] - Pb[inputs["body"].skeleton.index("Foot.L")]) > 0.05 * size
    assert sk.names[sk.parents[foot]] == inputs["body"].skeleton.names[inputs["body"].skeleton.parents[
        inputs["body"].skeleton.index("Foot.L")]]  # the target's parent, as every fused joint


def test_a_detached_foot_can_be_brought_onto_the_targets(tmp_path):
    path = corpus_case("leg_swap__EnemyLarge__Leela", tmp_path)
    path.write_text(path.read_text() + "\n[positioning]\ndetached_with_limb = false\n")
    cfg = load_config(path)
    inputs = load_characters(cfg)
    plan = plan_operations(inputs, cfg)
    assert plan.report["characters"]["donor"]["moved_with_limb"] == []
    sk = plan.skeleton
    Pb = plan.positioned["body"].skeleton.rest_worlds()[:, :3, 3]
    body = inputs["body"].skeleton
    assert np.allclose(sk.rest_worlds()[sk.index("Foot.L"), :3, 3], Pb[body.index("Foot.L")])


def test_a_detached_part_of_a_limb_replaced_by_itself_stays_put(tmp_path):
    cfg = load_config(corpus_case("identity__Leela__UpperLeg.L", tmp_path))
    inputs = load_characters(cfg)
    plan = plan_operations(inputs, cfg)
    assert not plan.translations["donor"].any()
    body = inputs["body"].skeleton
    assert np.array_equal(plan.skeleton.translations[plan.output_index("body", body.index("Foot.L"))],
                          rebase(inputs["body"]).skeleton.translations[body.index("Foot.L")])
