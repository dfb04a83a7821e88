"""Bone-to-bone mappings B_i with confidence (PIPELINE.md section 2)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import asset

from rigmix.config import load_config
from rigmix.io import load_character
from rigmix.mapping import (
    BoneMap,
    hop_distances,
    map_bones,
    paper_score,
    propagate,
    prototype_score,
    skeleton_features,
)
from rigmix.operations import plan_operations

CONFIGS = Path(__file__).parent / "configs"
FILES = {"CesiumMan.glb": "CesiumMan", "RiggedFigure.glb": "RiggedFigure", "Fox.glb": "Fox",
         "Horse.glb": "Horse", "KnightCharacter.glb": "Knight", "Velociraptor.glb": "Velociraptor"}


@pytest.fixture(scope="module")
def real():
    return {n: load_character(asset(n)) for n in set(FILES.values())}


@pytest.fixture(scope="module")
def plans(real):
    out = {}
    for f in sorted(CONFIGS.glob("*.toml")):
        cfg = load_config(f)
        inputs = {cid: real[FILES[Path(c.path).name]] for cid, c in cfg.characters.items()}
        out[f.stem] = plan_operations(inputs, cfg)
    return out


def random_tree(rng, J):
    parents = np.array([-1] + [int(rng.integers(0, j)) for j in range(1, J)])
    return parents, rng.normal(size=(J, 3))


# --------------------------------------------------------------------------------------------
# Features and scores
# --------------------------------------------------------------------------------------------


def test_parametric_position_on_a_chain_and_a_fork():
    P = np.array([[0, 0, 0], [0, 1, 0], [0, 2, 0], [0, 4, 0]], float)
    f = skeleton_features([-1, 0, 1, 2], P)
    assert np.allclose(f.param, [0, 0.25, 0.5, 1.0])
    assert np.allclose(f.arc, [0, 1, 2, 4]) and f.max_path == 4
    assert np.array_equal(f.children, [1, 1, 1, 0])
    # a fork: joint 1 lies on two paths of total length 2 and 4
    P = np.array([[0, 0, 0], [0, 1, 0], [1, 1, 0], [0, 4, 0]], float)
    f = skeleton_features([-1, 0, 1, 1], P)
    assert f.param[1] == pytest.approx(0.5 * (1 / 2 + 1 / 4))
    assert np.allclose(f.local_dir[3], [0, 1, 0]) and np.allclose(f.root_dir[2], [1, 1, 0] / np.sqrt(2))


def test_hops():
    H = hop_distances([-1, 0, 1, 1, -1])
    assert H[2, 3] == 2 and H[0, 3] == 2 and H[0, 0] == 0 and np.isinf(H[0, 4])


@pytest.mark.parametrize("score", [paper_score, prototype_score])
def test_scores_in_unit_interval_and_one_for_the_exact_match(score):
    rng = np.random.default_rng(1)
    for _ in range(5):
        parents, P = random_tree(rng, 12)
        f = skeleton_features(parents, P)
        H = hop_distances(parents)
        for i in range(1, 12):
            s = score(f, i, f, H[parents[i]])
            assert np.all(s >= -1e-12) and np.all(s <= 1 + 1e-12)
            # the same skeleton: joint i scored from its parent's image is exactly itself
            assert s[i] == pytest.approx(1.0)
            assert int(np.argmax(s)) == i or s[int(np.argmax(s))] == pytest.approx(1.0)


def test_injectivity_bonus_spreads_identical_candidates():
    # two input children at the same place, two output children at the same place
    P = np.array([[0, 0, 0], [0, 1, 0], [0, 1, 0]], float)
    parents = [-1, 0, 0]
    init = np.array([0, -1, -1])
    t, c = propagate(parents, P, init, parents, P, injectivity_bonus=(0.0, 0.0))
    assert t[1] == t[2]  # without the bonus both pick the same joint
    t, c = propagate(parents, P, init, parents, P)
    assert sorted(t[1:]) == [1, 2] and np.allclose(c, 1)


def test_secondary_roots_map_by_side():
    # main tree (root, spine) plus two separate IK roots at +x and -x; the input lists its IK
    # roots in the other order: each must find the output root on its own side (the paper's
    # score; the prototype's candidates are the image's ancestors and descendants only)
    Pout = np.array([[0, 0, 0], [0, 1, 0], [1, -1, 0], [-1, -1, 0]], float)
    Pin = Pout[[0, 1, 3, 2]]
    parents = [-1, 0, -1, -1]
    t, c = propagate(parents, Pin, np.array([0, 1, -1, -1]), parents, Pout)
    assert t[2] == 3 and t[3] == 2
    f = skeleton_features(parents, Pout)
    assert np.allclose(f.local_dir[2], np.array([1, -1, 0]) / np.sqrt(2))
    assert np.allclose(f.root_dir[3], f.local_dir[3]) and not f.local_dir[0].any()


def test_mirrored_horse_ik_roots_keep_their_side():
    # the mirrored Horse's IK roots are separate trees, whose left and right roots tie unless the
    # features link them to the main root; each must keep its side, or the donor's foot weights
    # drive the other leg's IK joint
    from rigmix.config import Config
    from rigmix.pipeline import compose

    path = asset("Horse")
    cfg = Config.model_validate({
        "name": "mirrored_back_leg",
        "characters": {"body": {"path": str(path)}, "donor": {"path": str(path), "mirror": True, "scale": 1.0}},
        "actions": [{"op": "replace", "source": "donor", "source_joint": "BackUpperLeg.L", "target": "body",
                     "target_joint": "BackUpperLeg.L", "mode": "blend"}],
    })
    comp = compose(cfg, until="mapping")
    names = comp.plan.positioned["donor"].skeleton.names
    out = comp.skeleton.names
    bm = comp.maps["donor"]
    ik = [j for j, n in enumerate(names) if n.startswith(("IK", "FF"))]
    assert len(ik) == 8
    assert [out[bm.target[j]] for j in ik] == [names[j] for j in ik]


def test_prototype_candidates_are_ancestors_or_descendants():
    # output: root with two branches; input joint 2 hangs below joint 1 which maps to branch A
    Pout = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [-1, 0, 0], [-2, 0, 0]], float)
    parents_out = [-1, 0, 1, 0, 3]
    Pin = np.array([[0, 0, 0], [1, 0, 0], [-2, 0, 0]], float)  # geometry points at branch B
    t, _ = propagate([-1, 0, 1], Pin, np.array([0, 1, -1]), parents_out, Pout, score="prototype")
    assert t[2] == 2  # restricted to 0, 1, 2; the best of those
    t, _ = propagate([-1, 0, 1], Pin, np.array([0, 1, -1]), parents_out, Pout, score="paper")
    assert t[2] == 4  # the paper's score may jump to the other branch (the geometry points there)
    with pytest.raises(ValueError, match="unknown score"):
        propagate([-1], Pin[:1], np.array([0]), [-1], Pout[:1], score="best")


def test_bonemap_is_frozen_and_reindexes():
    bm = BoneMap("x", [2, 0, -1], [1.0, 0.5, 0.0])
    with pytest.raises(ValueError):
        bm.target[0] = 1
    B = bm.matrix(3)
    assert np.array_equal(B, [[0, 0, 1], [1, 0, 0], [0, 0, 0]])
    with pytest.raises(ValueError):
        BoneMap("x", [0, 1], [1.0])


# --------------------------------------------------------------------------------------------
# Real compositions
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("score", ["paper", "prototype"])
def test_self_composition_maps_every_joint_to_its_copy(plans, real, score):
    plan = plans["self_composition"]
    maps = map_bones(plan, score=score)
    names = real["CesiumMan"].skeleton.names
    for cid in ("body", "donor"):
        bm = maps[cid]
        assert [plan.skeleton.names[t] for t in bm.target] == list(names)
        assert np.allclose(bm.confidence, 1.0, atol=1e-9)


@pytest.mark.parametrize("score", ["paper", "prototype"])
def test_cesium_arm_replaced_by_figure_arm(plans, real, score):
    plan = plans["limb_swap"]
    maps = map_bones(plan, score=score)
    cm = real["CesiumMan"].skeleton
    out = plan.skeleton.names
    bm = maps["cesium"]
    expect = {
        "Skeleton_arm_joint_L__4_": "Skeleton_arm_joint_L__4_",  # upper arm: the fused joint
        "Skeleton_arm_joint_L__3_": "arm_joint_L_2",  # forearm
        "Skeleton_arm_joint_L__2_": "arm_joint_L_3",  # hand
        "leg_joint_R_2": "leg_joint_R_2",  # the swapped leg (same names in both files)
        "leg_joint_R_5": "leg_joint_R_5",
    }
    for src, dst in expect.items():
        j = cm.index(src)
        assert out[bm.target[j]] == dst
        assert plan.provenance[bm.target[j]][0][0] == "figure" or src == "Skeleton_arm_joint_L__4_"
        assert 0.9 < bm.confidence[j] <= 1.0
    # every kept joint maps to its own copy with confidence 1
    kept = plan.used["cesium"]
    assert np.array_equal(bm.target[kept], plan.image["cesium"][kept])
    assert np.all(bm.confidence[kept] == 1.0)


@pytest.mark.parametrize("score", ["paper", "prototype"])
def test_maps_are_complete_on_every_config(plans, score):
    for name, plan in plans.items():
        maps = map_bones(plan, score=score)
        assert list(maps) == list(plan.image)
        for cid, bm in maps.items():
            J = plan.positioned[cid].skeleton.num_joints
            assert bm.target.shape == (J,) and bm.source == cid
            assert np.all(bm.target >= 0), name  # roots are linked: everything is reachable
            assert np.all((bm.confidence >= 0) & (bm.confidence <= 1))
            used = plan.used[cid]
            assert np.all(bm.confidence[used] == 1.0) and np.array_equal(bm.target[used], plan.image[cid][used])
            # confidence never grows along propagation: every unmapped joint is below 1
            assert np.all(bm.confidence[~used] < 1.0 + 1e-12)


def test_centaur_head_follows_the_new_torso(plans):
    plan = plans["centaur"]
    bm = map_bones(plan)["horse"]
    horse = plan.positioned["horse"].skeleton
    out = plan.skeleton
    # the horse's dropped neck and head map into the knight's torso subtree, not elsewhere
    torso = out.subtree(plan.image["horse"][horse.index("Neck1")])
    for name in ("Neck2", "Neck3", "Head"):
        assert torso[bm.target[horse.index(name)]], name


def test_cli_map_table_and_json(capsys):
    from rigmix.cli import main

    asset("CesiumMan"), asset("RiggedFigure")
    assert main(["map", str(CONFIGS / "limb_swap.toml"), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    rows = {(r["character"], r["input_joint"]): r for r in d["mapping"]}
    r = rows[("cesium", "Skeleton_arm_joint_L__3_")]
    assert r["output_joint"] == "arm_joint_L_2" and 0.9 < r["confidence"] <= 1
    assert len(d["mapping"]) == 38 and len(d["output_joints"]) == 19
    assert d["operations"]["characters"]["figure"]["scale_method"] == "limb-length"
    assert main(["map", str(CONFIGS / "limb_swap.toml")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["character", "input", "joint", "output", "joint", "confidence"]
    assert any(line.split()[:3] == ["cesium", "Skeleton_arm_joint_L__2_", "arm_joint_L_3"] for line in lines)


def test_example_configs_compose_on_builtin_characters():
    """Every examples/*.toml (built-in characters, no files) plans and maps."""
    from rigmix.pipeline import compose

    files = sorted((Path(__file__).parent.parent / "examples").glob("*.toml"))
    assert files
    for f in files:
        comp = compose(f, until="mapping")
        sk = comp.skeleton
        assert len(set(sk.names)) == sk.num_joints and np.all(sk.parents < np.arange(sk.num_joints))
        for cid, bm in comp.maps.items():
            assert np.all(bm.target >= 0) and np.all((bm.confidence >= 0) & (bm.confidence <= 1))
            assert np.all(bm.confidence[comp.plan.used[cid]] == 1)
        if f.stem == "self_arm":
            h = comp.inputs["body"].skeleton
            assert sk.names == h.names and all(np.array_equal(bm.target, np.arange(h.num_joints))
                                               for bm in comp.maps.values())
        if f.stem == "beast_arms":  # two fused pairs moved the quadruped by a non-rigid field
            t = comp.plan.translations["animal"]
            assert not np.allclose(t, t[0])


def test_hop_distances_of_a_tiny_skeleton():
    """scipy picks Floyd-Warshall for a small graph, which refuses a COO matrix: SimpleSkin's
    two joints gave "csgraph must be lil, csr, or csc format" (exit 1) in every composition."""
    from rigmix.mapping import hop_distances

    assert np.array_equal(hop_distances(np.array([-1, 0])), [[0, 1], [1, 0]])
    d = hop_distances(np.array([-1, 0, 1, -1]))
    assert d[0, 2] == 2 and np.isinf(d[0, 3]) and d[3, 3] == 0
