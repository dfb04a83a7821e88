"""Issue 27's band-fill protocol 1: a limb's bands hidden together with its mirror partner's."""

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
    character_arrays,
    mirror_joint_pairs,
    pair_band,
    pair_band_errors,
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


def test_pair_errors_measure_the_hidden_rows(fox):
    V, F, W, names, positions = character_arrays(fox)
    pairs, _ = mirror_joint_pairs(fox)
    errors = pair_band_errors(V, F, W, pairs[:2], "nearest", names=names)
    assert errors
    for key, e in errors.items():
        j, k = key.split("|")
        assert j in names and k in names
        assert 0 < e["mean"] <= e["max"] <= 1 and e["rows"] > 0


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
