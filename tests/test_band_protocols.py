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
