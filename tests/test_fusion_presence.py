"""Presence, secondary components and preserved faces (PIPELINE.md section 3)."""

import numpy as np
from fusion_shapes import ellipsoid, split_faces, two_joint_weights

from rigmix.fusion.meshutil import boundary_halfedges, edges_to_loops, face_adjacency, triangle_min_angles
from rigmix.fusion.presence import (
    classify_components,
    compute_presence,
    morphological_clean,
    raw_presence,
    smooth_presence,
)


def test_raw_presence_sums_used_joints():
    W = np.array([[0.2, 0.3, 0.5], [1.0, 0.0, 0.0], [np.nan, 0.5, 0.5]])
    p = raw_presence(W, np.array([False, True, True]))
    assert np.allclose(p, [0.8, 0.0, 1.0])


def test_smoothing_keeps_snapped_values_and_stays_in_range():
    V, F = ellipsoid((1.5, 0.4, 0.4))
    rng = np.random.default_rng(0)
    p = np.clip(two_joint_weights(V)[:, 1] + 0.05 * rng.standard_normal(len(V)), 0, 1)
    q = smooth_presence(p, F)
    assert np.all(q[p < 0.02] == 0) and np.all(q[p > 0.98] == 1)
    assert q.min() >= 0 and q.max() <= 1
    # smoothing lowers the roughness of the free values
    A = face_adjacency(F)
    assert A.shape == (len(F), len(F))
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]]])
    assert np.abs(np.diff(q[E], axis=1)).mean() < np.abs(np.diff(p[E], axis=1)).mean()


def test_presence_on_split_mesh_equals_welded():
    V, F = ellipsoid((1.5, 0.4, 0.4))
    W = two_joint_weights(V)
    used = np.array([True, False])
    a = compute_presence(V, F, W, used)
    Vs, Fs = split_faces(V, F)
    b = compute_presence(Vs, Fs, W[F.ravel()], used)
    assert np.allclose(b.p, a.p[F.ravel()])
    assert np.array_equal(a.preserved, b.preserved)
    assert a.preserved.any() and a.junction.any() and a.absent.any()
    # preserved faces are the presence-1 side, absent ones the other
    cx = V[F].mean(axis=1)[:, 0]
    assert cx[a.preserved].max() < cx[a.absent].min()


def test_secondary_components_kept_or_dropped_whole():
    V1, F1 = ellipsoid((1.5, 0.4, 0.4))
    V2, F2 = ellipsoid((0.2, 0.2, 0.2), center=(0, 1.0, 0), subdivisions=2)   # a prop on joint 0
    V3, F3 = ellipsoid((0.2, 0.2, 0.2), center=(1.0, 1.0, 0), subdivisions=2)  # a prop on joint 1
    V = np.concatenate([V1, V2, V3])
    F = np.concatenate([F1, F2 + len(V1), F3 + len(V1) + len(V2)])
    W = two_joint_weights(V1)
    W = np.concatenate([W, np.tile([0.9, 0.1], (len(V2), 1)), np.tile([0.1, 0.9], (len(V3), 1))])
    P = compute_presence(V, F, W, np.array([True, False]))
    body, prop0, prop1 = np.split(np.arange(len(F)), [len(F1), len(F1) + len(F2)])
    assert P.preserved[prop0].all() and not P.junction[prop0].any()
    assert P.absent[prop1].all()
    assert P.junction[body].any()  # the body is blended, never secondary
    labels, decision = classify_components(P.p_welded, P.welded.F)
    assert sorted(decision.tolist()) == [-1, 0, 1]


def test_morphology_removes_specks_and_fills_pinholes():
    V, F = ellipsoid((1, 1, 1), subdivisions=3)
    A = face_adjacency(F)
    cx = V[F].mean(axis=1)
    mask = cx[:, 0] > 0
    rng = np.random.default_rng(1)
    noisy = mask.copy()
    flip = rng.choice(len(F), 8, replace=False)
    noisy[flip] = ~noisy[flip]
    clean = morphological_clean(noisy, A, rounds=2)
    far = np.abs(cx[:, 0]) > 0.4  # away from the real border the result is exact
    assert np.array_equal(clean[far], mask[far])


def test_loops_and_angles_helpers():
    V, F = ellipsoid((1, 1, 1), subdivisions=2)
    keep = V[F].mean(axis=1)[:, 2] > 0.1
    loops, closed = edges_to_loops(boundary_halfedges(F[keep]))
    assert len(loops) == 1 and closed[0]
    ang = triangle_min_angles(V, F)
    assert 30 < ang.min() <= 60 and ang.max() <= 60 + 1e-9


def test_rigid_piece_on_a_replaced_joint_goes_with_the_part():
    """A replace's target keeps its fused joint, but a rigid piece riding on it (a robot's thigh
    plate) belongs to the replaced part: dropped whole. The skinned body across that joint stays
    blended, and a piece on another kept joint stays."""
    V1, F1 = ellipsoid((1.5, 0.4, 0.4))
    V2, F2 = ellipsoid((0.2, 0.2, 0.2), center=(0, 1.0, 0), subdivisions=2)   # a piece on joint 0
    V3, F3 = ellipsoid((0.2, 0.2, 0.2), center=(1.0, 1.0, 0), subdivisions=2)  # a piece on joint 1
    V = np.concatenate([V1, V2, V3])
    F = np.concatenate([F1, F2 + len(V1), F3 + len(V1) + len(V2)])
    W = np.concatenate([two_joint_weights(V1), np.tile([1.0, 0.0], (len(V2), 1)), np.tile([0.0, 1.0], (len(V3), 1))])
    used = np.array([True, True])
    body, piece0, piece1 = np.split(np.arange(len(F)), [len(F1), len(F1) + len(F2)])
    kept = compute_presence(V, F, W, used)
    assert kept.preserved[piece1].all() and kept.preserved[body].all()
    P = compute_presence(V, F, W, used, replaced=np.array([False, True]))
    assert P.absent[piece1].all() and not P.preserved[piece1].any()
    assert P.preserved[piece0].all()
    assert np.array_equal(P.preserved[body], kept.preserved[body])  # the body's faces are not affected
