"""Issue 27's band-fill protocols: 1, a limb's bands hidden together with its mirror partner's; 2, the
same while similar parts stay painted; 3, a tail or wing chain whose painting is nowhere known."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from conftest import ROOT, asset

from rigmix.io import load_character
from rigmix.limbs import classify_limbs

sys.path.insert(0, str(ROOT))
from benchmarks.band_fill import (  # noqa: E402
    HIGH,
    LOW,
    ambient_cases,
    character_arrays,
    clip_matrices,
    mask_errors,
    mirror_joint_pairs,
    pair_band,
    protocol_masks,
    rest_diagonal,
    similar_part_cases,
    skinned_error,
    welded_truth,
)


@pytest.fixture(scope="module")
def fox():
    return load_character(asset("Fox"))


def test_pairs_join_each_limb_to_its_partner(fox):
    pairs, limbs = mirror_joint_pairs(fox)
    plan = classify_limbs(fox)
    names = list(fox.skeleton.names)
    assert len(limbs) == 2  # the Fox's arms and legs
    for root, partner in limbs:
        assert plan.limb(root).partner == partner
    for j, k in pairs:
        a = next(limb for limb in plan.limbs if names[j] in limb.joints)
        b = next(limb for limb in plan.limbs if names[k] in limb.joints)
        assert a.partner == b.root and a.side != b.side


def test_both_bands_hidden(fox):
    """The hidden rows cover the limb's band and its partner's, on both sides of the body."""
    V, F, W, names, positions = character_arrays(fox)
    index, Wt = welded_truth(V, F, W)
    Pw = np.zeros((len(Wt), 3))
    Pw[index] = V
    pairs, _ = mirror_joint_pairs(fox)
    axis = classify_limbs(fox).symmetry_axis
    checked = 0
    for j, k in pairs:
        in_j = (Wt[:, j] > LOW) & (Wt[:, j] < HIGH)
        in_k = (Wt[:, k] > LOW) & (Wt[:, k] < HIGH)
        if not (in_j.any() and in_k.any()):
            continue
        band = pair_band(Wt, j, k)
        assert band[in_j].all() and band[in_k].all()
        # the two bands lie on opposite sides of the body
        side_j = np.sign(np.median(Pw[in_j, axis] - np.median(Pw[:, axis])))
        side_k = np.sign(np.median(Pw[in_k, axis] - np.median(Pw[:, axis])))
        assert side_j == -side_k != 0
        checked += 1
    assert checked >= 4


def test_pair_errors_measure_the_hidden_rows_and_their_skinning(fox):
    """Protocol 1's cases are the joint pairs with a band on both sides, each measured in weights
    and skinned under the Fox's clips."""
    V, F, W, names, positions = character_arrays(fox)
    index, Wt = welded_truth(V, F, W)
    masks = protocol_masks(fox, Wt, "both_hidden")
    pairs, _ = mirror_joint_pairs(fox)
    both = [(j, k) for j, k in pairs
            if ((Wt[:, j] > LOW) & (Wt[:, j] < HIGH)).any() and ((Wt[:, k] > LOW) & (Wt[:, k] < HIGH)).any()]
    assert sorted(masks) == sorted(f"{names[j]}|{names[k]}" for j, k in both)
    for j, k in both:
        assert (masks[f"{names[j]}|{names[k]}"] == pair_band(Wt, j, k)).all()
    skin = clip_matrices(fox)
    errors = mask_errors(V, F, W, dict(list(masks.items())[:2]), "nearest", skin=skin,
                         diagonal=rest_diagonal(fox.skeleton, V, W))
    assert len(errors) == 2
    for key, e in errors.items():
        assert e["rows"] == masks[key].sum() > 0
        assert 0 < e["mean"] <= e["max"] <= 1
        assert 0 < e["skinned"] <= e["skinned_max"] < 1  # a fraction of the diagonal


@pytest.fixture(scope="module")
def knight_hidden():
    """The Knight with its first mirrored joint pair's two bands hidden (protocol 1)."""
    character = load_character(asset("Knight"))
    V, F, W, names, positions = character_arrays(character)
    index, Wt = welded_truth(V, F, W)
    pairs, _ = mirror_joint_pairs(character)
    band = next(b for b in (pair_band(Wt, j, k) for j, k in pairs) if b.sum() > 20)
    return {"character": character, "V": V, "F": F, "W": W, "names": names, "positions": positions,
            "parents": character.skeleton.parents, "unknown": band[index]}


def test_bone_owners_follow_the_painting(knight_hidden):
    """A vertex painted to one joint has that joint's bone among its two nearest."""
    from rigmix.weights.borrow import bone_owners

    d = knight_hidden
    owners = bone_owners(d["V"], d["positions"], d["parents"])
    single = d["W"].max(axis=1) > 0.95
    joint = d["W"].argmax(axis=1)
    hit = (owners[single] == joint[single, None]).any(axis=1)
    assert single.sum() > 500 and hit.mean() > 0.9


def test_fill_borrows_from_feature_similar_parts(knight_hidden):
    from dfd.encoders import SkeletonEncoder, bone_segments, point_field
    from rigmix.weights import fill_weights
    from rigmix.weights.borrow import bone_owners, borrow_prior
    from rigmix.weights.mesh import weld_rows, welded_mesh
    from rigmix.weights.mirror import mirror_joints, symmetry_plane

    d = knight_hidden
    V, F, W, unknown = d["V"], d["F"], d["W"], d["unknown"]
    field = point_field(SkeletonEncoder(*bone_segments(d["positions"], d["parents"]), describe=False), V)
    g = welded_mesh(V, F)
    Ww, unk = weld_rows(np.where(unknown[:, None], 0.0, W), g.index, unknown, len(g.V))
    mirror = mirror_joints(names=d["names"], positions=d["positions"], plane=symmetry_plane(g.V, g.F))
    P, c = borrow_prior(g, Ww, unk, field(g.V), d["positions"], d["parents"], mirror, confidence=0.5)
    assert (c[~unk] == 0).all() and (P[~unk] == 0).all()
    assert 0 <= c.min() and c.max() <= 0.5 and (c[unk] > 0).any()
    # each prior row lives on the row's two bone owners and sums to 1
    owners = bone_owners(g.V, d["positions"], d["parents"])
    rows = np.flatnonzero(c > 0)
    np.testing.assert_allclose(P[rows].sum(axis=1), 1.0, atol=1e-9)
    outside = P[rows].copy()
    outside[np.arange(len(rows))[:, None], owners[rows]] = 0.0
    assert (outside == 0).all()
    skeleton = {"joint_positions": d["positions"], "joint_names": d["names"], "joint_parents": d["parents"]}
    hidden = np.where(unknown[:, None], 0.0, W)
    with_borrow = fill_weights(V, F, hidden, unknown, method="dfd", field=field, borrow=0.5, **skeleton)
    without = fill_weights(V, F, hidden, unknown, method="dfd", field=field, **skeleton)
    np.testing.assert_array_equal(with_borrow[~unknown], W[~unknown])
    np.testing.assert_allclose(with_borrow[unknown].sum(axis=1), 1.0, atol=1e-9)
    assert np.isfinite(with_borrow).all() and (with_borrow >= 0).all()
    assert np.abs(with_borrow - without)[unknown].max() > 0.01  # the borrowed prior takes part


# --- protocol 2: similar parts stay painted ------------------------------------------------------


@pytest.fixture(scope="module")
def horse():
    return load_character(asset("Horse"))


def test_similar_hides_a_front_pair_while_back_legs_stay_painted(horse):
    names = list(horse.skeleton.names)
    cases = {c["name"]: c for c in similar_part_cases(horse)}
    front = cases["FrontUpperLeg.L|FrontUpperLeg.R"]
    assert set(front["painted"]) == {"BackUpperLeg.L", "BackUpperLeg.R"}
    hidden = {names[j] for j in front["joints"]}
    assert {"FrontUpperLeg.L", "FrontLowerLeg.L", "FrontUpperLeg.R", "FrontLowerLeg.R"} <= hidden
    assert not any(n.startswith("Back") for n in hidden)
    V, F, W, _, _ = character_arrays(horse)
    index, Wt = welded_truth(V, F, W)
    mask = protocol_masks(horse, Wt, "similar")[front["name"]]
    # both front legs' bands are hidden, together ...
    for n in ("FrontUpperLeg.L", "FrontUpperLeg.R", "FrontLowerLeg.L", "FrontLowerLeg.R"):
        j = names.index(n)
        assert mask[(Wt[:, j] > LOW) & (Wt[:, j] < HIGH)].all()
    # ... and the back legs keep all their painting
    back = [names.index(n) for n in names if n.startswith("BackUpperLeg") or n.startswith("BackLowerLeg")]
    assert Wt[mask][:, back].max() < LOW
    assert (Wt[~mask][:, back] > HIGH).any()


def test_similar_cases_on_the_wasp_hide_one_leg_pair_of_three():
    wasp = load_character(asset("Wasp"))
    plan = classify_limbs(wasp)
    legs = {limb.root for limb in plan.of_kind("leg")}
    pairs = [c for c in similar_part_cases(wasp) if c["kind"] == "leg"]
    assert len(legs) == 6 and len(pairs) == 3
    for c in pairs:
        hidden = set(c["name"].split("|"))
        assert len(hidden) == 2 and hidden <= legs
        assert set(c["painted"]) == legs - hidden  # the two other pairs stay painted
    tail = [c for c in similar_part_cases(wasp) if c["kind"] == "tail segment"]
    assert len(tail) == 1 and len(tail[0]["joints"]) == 1 and len(tail[0]["painted"]) >= 2


def test_similar_errors_measure_the_hidden_rows_and_their_skinning(horse):
    V, F, W, names, _ = character_arrays(horse)
    index, Wt = welded_truth(V, F, W)
    masks = protocol_masks(horse, Wt, "similar")
    skin = clip_matrices(horse)
    errors = mask_errors(V, F, W, masks, "nearest", skin=skin, diagonal=rest_diagonal(horse.skeleton, V, W))
    assert set(errors) == set(masks)
    for key, e in errors.items():
        assert e["rows"] == masks[key].sum() > 0
        assert 0 < e["mean"] <= e["max"] <= 1
        assert 0 < e["skinned"] <= e["skinned_max"] < 1  # a fraction of the diagonal


def test_skinned_error_of_a_rigid_offset():
    """Weights moved wholly onto a joint translated by t: every vertex is off by |t|."""
    rng = np.random.default_rng(0)
    V = rng.normal(size=(20, 3))
    M = np.zeros((3, 2, 3, 4))
    M[..., :3] = np.eye(3)
    t = np.array([0.3, -0.4, 0.0])
    M[:, 1, :, 3] = t
    W0 = np.tile([1.0, 0.0], (20, 1))
    W1 = np.tile([0.0, 1.0], (20, 1))
    assert skinned_error(V, W0, W0, M, 1.0) == (0.0, 0.0)
    mean, worst = skinned_error(V, W0, W1, M, 2.0)
    assert mean == pytest.approx(0.25) and worst == pytest.approx(0.25)


# --- protocol 3: ambient handles -------------------------------------------------------------------


def test_ambient_hides_a_whole_tail_chain(horse):
    names = list(horse.skeleton.names)
    plan = classify_limbs(horse)
    (tail,) = plan.of_kind("tail")
    (case,) = ambient_cases(horse)
    assert case["kind"] == "tail" and {names[j] for j in case["joints"]} == set(tail.joints)
    V, F, W, _, _ = character_arrays(horse)
    index, Wt = welded_truth(V, F, W)
    mask = protocol_masks(horse, Wt, "ambient")[case["name"]]
    # nowhere known: no vertex left painted carries any tail joint
    assert (Wt[~mask][:, case["joints"]] == 0).all()
    assert mask.sum() > 50 and mask[Wt[:, names.index(tail.joints[-1])] > 0].all()


def test_ambient_cases_pair_wings():
    wasp = load_character(asset("Wasp"))
    kinds = {c["kind"]: c for c in ambient_cases(wasp)}
    names = list(wasp.skeleton.names)
    wings = {names[j] for j in kinds["wing"]["joints"]}
    plan = classify_limbs(wasp)
    assert wings == {n for limb in plan.of_kind("wing") for n in limb.joints}
    assert {limb.side for limb in plan.of_kind("wing")} == {"L", "R"}


def test_bone_samples_lie_on_the_bones():
    from rigmix.weights.ambient import bone_samples

    positions = np.array([[0.0, 0, 0], [0, 1, 0], [0, 3, 0]])
    parents = np.array([-1, 0, 1])
    X = bone_samples(positions, parents, 1, samples=4)
    np.testing.assert_allclose(X, [[0, 1, 0], [0, 1.5, 0], [0, 2, 0], [0, 2.5, 0]])
    tip = bone_samples(positions, parents, 2, samples=2)  # a leaf continues its parent's bone
    np.testing.assert_allclose(tip, [[0, 3, 0], [0, 3.5, 0]])


def test_ambient_prior_brings_back_a_tail_nowhere_known(horse):
    from dfd.encoders import SkeletonEncoder, bone_segments, point_field
    from rigmix.weights import fill_weights
    from rigmix.weights.ambient import ambient_prior
    from rigmix.weights.mesh import weld_rows, welded_mesh

    V, F, W, names, positions = character_arrays(horse)
    parents = horse.skeleton.parents
    index, Wt = welded_truth(V, F, W)
    (case,) = ambient_cases(horse)
    unknown = protocol_masks(horse, Wt, "ambient")[case["name"]][index]
    field = point_field(SkeletonEncoder(*bone_segments(positions, parents)), V)
    g = welded_mesh(V, F)
    Ww, unk = weld_rows(np.where(unknown[:, None], 0.0, W), g.index, unknown, len(g.V))
    deforming = W.sum(axis=0) > 0
    f = field(g.V)
    P, c = ambient_prior(g, Ww, unk, f, field, positions, parents, deforming, confidence=0.5)
    assert (c[~unk] == 0).all() and (P[~unk] == 0).all()
    assert 0 <= c.min() and c.max() <= 0.5 and (c[unk] > 0).all()
    np.testing.assert_allclose(P[unk].sum(axis=1), 1.0, atol=1e-9)
    assert P[unk][:, case["joints"]].sum(axis=1).mean() > 0.5  # the tail's handles take its region
    hidden = np.where(unknown[:, None], 0.0, W)
    skeleton = {"joint_positions": positions, "joint_names": names, "joint_parents": parents,
                "deforming_joints": deforming}
    filled = fill_weights(V, F, hidden, unknown, method="dfd", field=field, ambient=0.5, **skeleton)
    inpainted = fill_weights(V, F, hidden, unknown, method="inpaint")
    np.testing.assert_array_equal(filled[~unknown], W[~unknown])
    np.testing.assert_allclose(filled[unknown].sum(axis=1), 1.0, atol=1e-9)
    assert (filled >= 0).all()
    tail = case["joints"]
    assert filled[unknown][:, tail].sum() > 10 * inpainted[unknown][:, tail].sum()


def test_unknown_chains_keep_whole_chains_only():
    from rigmix.weights.ambient import unknown_chains

    # 0 root, 1 -> 2 -> 3 a tail, 4 a leg whose foot 5 stays painted
    parents = np.array([-1, 0, 1, 2, 0, 4])
    ambient = np.array([False, True, True, True, True, False])
    np.testing.assert_array_equal(unknown_chains(ambient, parents), [False, True, True, True, False, False])


def test_default_borrows_only_next_to_a_chain_nowhere_known(horse):
    """The pipeline's default (``ambient_borrow``) leaves protocol 2's fill as it was, and moves protocol 3's."""
    from rigmix.weights import fill_weights

    V, F, W, names, positions = character_arrays(horse)
    index, Wt = welded_truth(V, F, W)
    skeleton = {"joint_positions": positions, "joint_names": names, "joint_parents": horse.skeleton.parents,
                "deforming_joints": W.sum(axis=0) > 0}
    front = protocol_masks(horse, Wt, "similar")["FrontUpperLeg.L|FrontUpperLeg.R"][index]
    (tail,) = protocol_masks(horse, Wt, "ambient").values()
    tail = tail[index]
    for unknown, moved in ((front, False), (tail, True)):
        hidden = np.where(unknown[:, None], 0.0, W)
        default = fill_weights(V, F, hidden, unknown, method="dfd", field=False, ambient_borrow=0.5, **skeleton)
        plain = fill_weights(V, F, hidden, unknown, method="dfd", field=False, **skeleton)
        np.testing.assert_allclose(default[unknown].sum(axis=1), 1.0, atol=1e-9)
        assert (np.abs(default - plain).max() > 0.01) == moved


# --- protocol 1's run: the skinned error beside the weight error ------------------------------------


def test_protocol_one_reports_the_skinned_error_of_every_method():
    """Protocol 1 through the runner every protocol shares: each method has the weight and the
    skinned error, over the same joint pairs."""
    from benchmarks.band_fill import run_protocols

    result = run_protocols(asset("Fox"), protocols=("both_hidden",), encoders=(), direct=("skeleton-relative",))
    r = result["both_hidden"]
    assert {"nearest", "inpaint", "dfd_no_field", "dfd[skeleton-relative-direct]"} <= set(r["methods"])
    for label, m in r["methods"].items():
        assert set(m["per_case"]) == set(r["cases"])
        assert 0 < m["mean_error"] <= m["max_error"] <= 1
        assert 0 < m["skinned_error"] <= m["skinned_max"] < 1, label
    # the fill that reads the skeleton's bones is closer to the painting than the closest known vertex
    assert r["methods"]["dfd_no_field"]["mean_error"] < r["methods"]["nearest"]["mean_error"]


# --- the protocols on self-compositions ---------------------------------------------------------------


@pytest.fixture(scope="module")
def fox_self():
    """The Fox, its cases of protocols 1 and 3 on self-compositions, each composed once."""
    from benchmarks.self_composition import REBUILT, field_protocol_cases, self_config
    from rigmix.pipeline import compose

    fox = load_character(asset("Fox"))
    cases = {p: field_protocol_cases(fox, p) for p in ("both_hidden", "ambient")}
    comps = {c["joint"]: compose(self_config(asset("Fox"), c["joint"], fusion=REBUILT), until="completion")
             for p in ("both_hidden", "ambient") for c in cases[p][:1]}
    return {"character": fox, "cases": cases, "comps": comps}


def test_self_composition_protocol_one_composes_each_limb_root(fox_self):
    fox = fox_self["character"]
    _, limbs = mirror_joint_pairs(fox)
    cases = fox_self["cases"]["both_hidden"]
    assert [c["joint"] for c in cases] == [a for a, _ in limbs]
    for c, (a, b) in zip(cases, limbs):
        assert [fox.skeleton.names[j] for j in c["joints"]] == [a, b]


def test_self_composition_protocol_one_hides_the_partner_band_beside_the_junction(fox_self):
    """The hidden rows are the rebuilt junction's and the partner limb's root band, on the other
    side of the body: nothing is left for the mirror to copy."""
    from benchmarks.self_composition import field_case_rows, output_joints

    case = fox_self["cases"]["both_hidden"][0]
    comp = fox_self["comps"][case["joint"]]
    G, hidden, junction = field_case_rows(comp, case, "both_hidden")
    surface = comp.surface
    index, Gt = welded_truth(surface.V, surface.F, G)
    partner = output_joints(comp)[case["joints"][1]]
    in_band = (Gt[:, partner] > LOW) & (Gt[:, partner] < HIGH)
    assert in_band.any() and hidden[in_band].all()
    assert (hidden & ~junction).any()  # rows the hidden protocol (the junction alone) would keep
    # the partner's band and the junction lie on opposite sides of the symmetry plane
    axis = classify_limbs(fox_self["character"]).symmetry_axis
    P = np.zeros((len(Gt), 3))
    P[index] = surface.V
    mid = np.median(P[:, axis])
    assert np.sign(np.median(P[junction, axis]) - mid) == -np.sign(np.median(P[in_band, axis]) - mid)


def test_self_composition_protocol_three_leaves_the_tail_nowhere_known(fox_self):
    """Protocol 3 on a self-composition: no row outside the hidden ones carries a tail joint, and the
    fills are measured in weights and skinned under the Fox's clips."""
    from benchmarks.band_fill import protocol_methods
    from benchmarks.self_composition import field_case_errors, field_case_rows, output_joints

    case = fox_self["cases"]["ambient"][0]
    comp = fox_self["comps"][case["joint"]]
    G, hidden, junction = field_case_rows(comp, case, "ambient")
    surface = comp.surface
    index, Gt = welded_truth(surface.V, surface.F, G)
    tail = output_joints(comp)[case["joints"]]
    assert Gt[hidden][:, tail].sum(axis=1).max() > HIGH  # the tail's own rows are hidden ...
    assert Gt[~(hidden | junction)][:, tail].max() == 0  # ... and no known row carries it
    methods = {k: v for k, v in protocol_methods({}, "ambient").items() if k in ("nearest", "dfd_no_field")}
    res = field_case_errors(comp, case, "ambient", methods)
    assert res["rows"] == (hidden | junction).sum()
    for label, m in res["methods"].items():
        e = m["errors"]
        assert e["rows"] == res["rows"]
        assert 0 < e["mean"] <= e["max"] <= 1
        assert 0 < e["skinned"] <= e["skinned_max"] < 1, label
    # nearest cannot bring back a joint no known row carries; the bone prior can
    assert res["methods"]["dfd_no_field"]["errors"]["mean"] < res["methods"]["nearest"]["errors"]["mean"]
