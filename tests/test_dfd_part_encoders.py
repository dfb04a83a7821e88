"""Issue 27's part-aware encoders (dfd.encoders): skeleton-relative, heat kernel signature, combined."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from conftest import ROOT, asset
from scipy.spatial import cKDTree

from dfd.encoders import (
    CombinedEncoder,
    Encoder,
    FilterBankEncoder,
    HeatKernelEncoder,
    SkeletonEncoder,
    bone_segments,
    encode_views,
    get_encoder,
    view_points,
)
from dfd.errors import DfdInputError
from dfd.mesh import weld
from dfd.render import render_views, surface_points
from rigmix.io import load_character
from rigmix.limbs import classify_limbs
from rigmix.weights import symmetry_plane

sys.path.insert(0, str(ROOT))
from benchmarks.band_fill import character_arrays  # noqa: E402


@pytest.fixture(scope="module")
def knight():
    character = load_character(asset("Knight"))
    V, F, W, names, positions = character_arrays(character)
    Vw, index, Fw = weld(V, F)
    Ww = np.zeros((len(Vw), W.shape[1]))
    Ww[index] = W
    views = render_views(Vw, Fw, n_views=6, resolution=128)
    heads, tails = bone_segments(positions, character.skeleton.parents)
    return {"character": character, "V": Vw, "F": Fw, "W": Ww, "names": names, "views": views,
            "heads": heads, "tails": tails}


def _check_unit(X, views, dim):
    assert X.shape == views.mask.shape + (dim,) and X.dtype == np.float32
    assert np.isfinite(X).all()
    np.testing.assert_allclose(np.linalg.norm(X[views.mask], axis=1), 1.0, atol=1e-5)
    assert (X[~views.mask] == 0).all()


def test_view_points_are_the_surface_points(knight):
    views = knight["views"]
    P = view_points(views)
    S = surface_points(knight["V"], knight["F"], views)
    size = np.ptp(knight["V"], axis=0).max()
    assert np.abs(P[views.mask] - S).max() < 1e-4 * size


def test_skeleton_features_tell_an_arm_from_a_leg(knight):
    enc = get_encoder("skeleton", heads=knight["heads"], tails=knight["tails"])
    assert isinstance(enc, Encoder) and isinstance(enc, SkeletonEncoder)
    views = knight["views"]
    X = encode_views(enc, views)
    _check_unit(X, views, enc.feature_dim)
    # pixels on the left arm and on the left leg (limbs from the classifier, the joints'
    # weight over 0.9 at the pixel's nearest vertex) sit apart in feature space
    plan = classify_limbs(knight["character"])
    names = knight["names"]
    arm = next(limb for limb in plan.of_kind("arm") if limb.side == "L")
    leg = next(limb for limb in plan.of_kind("leg") if limb.side == "L")
    P = view_points(views)[views.mask]
    _, nearest = cKDTree(knight["V"]).query(P)
    W = knight["W"][nearest]
    on_arm = W[:, [names.index(n) for n in arm.joints]].sum(axis=1) > 0.9
    on_leg = W[:, [names.index(n) for n in leg.joints]].sum(axis=1) > 0.9
    assert on_arm.sum() > 50 and on_leg.sum() > 50
    Xa, Xl = X[views.mask][on_arm], X[views.mask][on_leg]

    def spread(A, B):
        return np.linalg.norm(A[:, None] - B[None], axis=2).mean()

    assert spread(Xa, Xl) > 1.4 * max(spread(Xa, Xa), spread(Xl, Xl))
    Y, label = np.vstack([Xa, Xl]), np.r_[np.zeros(len(Xa)), np.ones(len(Xl))]
    D = np.linalg.norm(Y[:, None] - Y[None], axis=2)
    np.fill_diagonal(D, np.inf)
    assert (label[D.argmin(axis=1)] == label).mean() > 0.98  # each pixel's nearest neighbour is on its limb
    # the first channels are the point in its nearest bone's frame: along the upper arm's bone,
    # just off it, the position along the bone runs from 0 to 1
    upper = names.index(arm.joints[0])
    positions = np.linalg.inv(knight["character"].skeleton.inverse_binds)[:, :3, 3]
    bone = int(np.argmin(np.linalg.norm(knight["heads"] - positions[upper], axis=1)
                         + np.linalg.norm(knight["tails"] - positions[names.index(arm.joints[1])], axis=1)))
    h, t = knight["heads"][bone], knight["tails"][bone]
    s = np.linspace(0.2, 0.8, 7)
    side = np.cross(t - h, [0.0, 0.0, 1.0])
    Q = h + s[:, None] * (t - h) + 0.05 * np.linalg.norm(t - h) * side / np.linalg.norm(side)
    along = enc.point_features(Q)[:, 0]
    np.testing.assert_allclose(along, s, atol=1e-6)
    with pytest.raises(DfdInputError, match="encode_views"):
        enc.encode(views.rgb)


def test_skeleton_encoder_rejects_bad_bones():
    with pytest.raises(DfdInputError, match=r"\(S, 3\)"):
        SkeletonEncoder(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(DfdInputError, match="NaN"):
        SkeletonEncoder(np.full((1, 3), np.nan), np.zeros((1, 3)))


def test_heat_kernel_signature_is_mirror_symmetric(knight):
    """An intrinsic signature: a vertex and its mirror image look alike, far more than two random vertices."""
    V, F = knight["V"], knight["F"]
    enc = HeatKernelEncoder(V, F, eigenpairs=24, times=6)
    views = knight["views"]
    X = encode_views(enc, views)
    _check_unit(X, views, 6)
    H = enc.point_features(V)
    assert H.shape == (len(V), 6) and np.isfinite(H).all()
    plane = symmetry_plane(V, F)
    _, mirror = cKDTree(V).query(plane.reflect(V))
    rng = np.random.default_rng(0)
    other = rng.permutation(len(V))
    mirrored = np.linalg.norm(H - H[mirror], axis=1).mean()
    random = np.linalg.norm(H - H[other], axis=1).mean()
    assert mirrored < 0.5 * random


def test_combined_encoder(knight):
    views = knight["views"]
    enc = CombinedEncoder([SkeletonEncoder(knight["heads"], knight["tails"]), FilterBankEncoder()], weights=[1, 1])
    X = encode_views(enc, views)
    _check_unit(X, views, enc.feature_dim)
    assert enc.feature_dim == 24 + 28 and enc.settings()["encoders"][0]["name"] == "skeleton"


def test_heat_kernel_signature_on_the_adventurer():
    """The corpus Adventurer's large cotangent weights once left the shift-invert factor singular."""
    from conftest import corpus

    V, F, *_ = character_arrays(load_character(corpus("Adventurer")))
    enc = HeatKernelEncoder(V, F)
    assert enc.vertex_hks.shape == (len(enc.V), 8) and np.isfinite(enc.vertex_hks).all()
    assert np.ptp(enc.vertex_hks, axis=0).min() > 0  # the signature varies over the surface
