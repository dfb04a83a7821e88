"""dfd.weights: the two similarity forms, feature-space constraints, geodesic locality."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import asset

from dfd.io import read_mesh
from dfd.shapes import grid, icosphere
from dfd.weights import UNREACHABLE, geodesic_distances, handle_weights, iter_handle_weights, similarity


def _unit(X):
    return X / np.linalg.norm(X, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def features():
    rng = np.random.default_rng(0)
    return _unit(rng.normal(size=(500, 16))).astype(np.float32), _unit(rng.normal(size=(7, 16))).astype(np.float32)


def test_distance_and_cosine_forms_match_their_definitions(features):
    X, H = features
    W = handle_weights(X, H, form="distance")
    ref = np.clip(1.0 - np.linalg.norm(X[:, None, :] - H[None, :, :], axis=2), 0.0, 1.0)
    np.testing.assert_allclose(W, ref, atol=2e-6)
    C = handle_weights(X, H, form="cosine")
    np.testing.assert_allclose(C, np.clip(X @ H.T, 0.0, 1.0), atol=2e-6)
    assert W.dtype == np.float32 and W.shape == (500, 7)
    # a vertex with the handle's own feature gets weight 1 in both forms
    np.testing.assert_allclose(handle_weights(H, H, form="distance").diagonal(), 1.0, atol=1e-3)
    np.testing.assert_allclose(handle_weights(H, H, form="cosine").diagonal(), 1.0, atol=1e-6)
    # the distance form is the stricter one (zero beyond 60 degrees)
    assert (W <= C + 1e-6).all()


def test_feature_space_constraints(features):
    X, H = features
    fixed = X[:3]
    W = handle_weights(X, H, fixed=fixed)
    plain = handle_weights(X, H)
    w_fixed = similarity(X, fixed).max(axis=1)
    np.testing.assert_allclose(W, np.maximum(0.0, plain - w_fixed[:, None]), atol=1e-6)
    assert (W[:3] == 0).all()  # the fixed points themselves never move


def test_locality_falls_off_monotonically_with_geodesic_distance():
    V, F = grid(31)
    corner = 0
    D = geodesic_distances(V, F, [corner])
    ones = np.ones((len(V), 4), dtype=np.float32) / 2.0
    for p in (0.5, 1.0, 2.0, 4.0):
        W = handle_weights(ones, ones[:1], geodesic=D, p=p)[:, 0]
        np.testing.assert_allclose(W, (1.0 - D[:, 0]) ** p, rtol=1e-5)
        order = np.argsort(D[:, 0], kind="stable")
        assert (np.diff(W[order]) <= 1e-7).all()  # non-increasing along distance
        assert W[corner] == pytest.approx(1.0)
    # a larger exponent is more local everywhere beyond the handle
    far = D[:, 0] > 0.05
    w1 = handle_weights(ones, ones[:1], geodesic=D, p=1.0)[far, 0]
    w4 = handle_weights(ones, ones[:1], geodesic=D, p=4.0)[far, 0]
    assert (w4 < w1).all()


def test_locality_scales_real_weights(features):
    X, H = features
    rng = np.random.default_rng(1)
    D = rng.uniform(0.0, 0.999, size=(len(X), len(H))).astype(np.float32)
    W = handle_weights(X, H, geodesic=D, p=2.0)
    np.testing.assert_allclose(W, handle_weights(X, H) * (1.0 - D) ** 2, atol=1e-6)
    with pytest.raises(ValueError, match="geodesic"):
        handle_weights(X, H, p=1.0)


def test_geodesic_distances_on_a_plane_are_euclidean():
    V, F = grid(41)
    sources = [0, 20 * 41 + 20]
    D = geodesic_distances(V, F, sources)
    assert D.shape == (len(V), 2) and D.dtype == np.float32
    assert (D >= 0).all() and (D < 1).all()
    E = np.linalg.norm(V[:, None, :] - V[sources][None, :, :], axis=2)
    E /= E.max()
    assert D[sources[0], 0] == 0 and D[sources[1], 1] == 0
    # heat method vs the exact distance, normalized the same way (largest value ~1); the heat
    # method smooths near the source: measured 0.031 (max) and 0.011 (mean) on this grid
    assert np.abs(D - E).max() < 0.05
    assert np.abs(D - E).mean() < 0.02


def test_geodesic_unreachable_components_and_seams():
    S, SF = icosphere(2)
    V = np.concatenate([S, S + [5.0, 0.0, 0.0]])
    F = np.concatenate([SF, SF + len(S)])
    D = geodesic_distances(V, F, [0])
    assert (D[len(S):, 0] == UNREACHABLE).all() and UNREACHABLE < 1.0
    assert D[: len(S), 0].max() < UNREACHABLE
    # split every face apart (as flat-shaded glTF assets are): same distances after welding
    Vs = S[SF].reshape(-1, 3)
    Fs = np.arange(len(Vs)).reshape(-1, 3)
    Ds = geodesic_distances(Vs, Fs, [int(np.flatnonzero(SF.ravel() == 0)[0])])
    np.testing.assert_allclose(Ds[:, 0], geodesic_distances(S, SF, [0])[SF.ravel(), 0], atol=1e-5)


def test_geodesic_on_a_split_character():
    """Fox: 1,728 split vertices, 576 raw components that weld into one."""
    mesh = read_mesh(asset("Fox"))
    D = geodesic_distances(mesh.V, mesh.F, [0, 100])
    assert D.max() < UNREACHABLE  # every vertex reached: the mesh was welded
    assert (D.max(axis=0) > 0.5).all()


def test_rows_on_demand_match_full_matrix(features):
    X, H = features
    D = np.random.default_rng(2).uniform(0, 0.99, size=(len(X), len(H))).astype(np.float32)
    full = handle_weights(X, H, form="cosine", fixed=X[:2], geodesic=D, p=1.5)
    parts = dict(iter_handle_weights(X, H, chunk=64, form="cosine", fixed=X[:2], geodesic=D, p=1.5))
    assert sorted(parts) == list(range(0, len(X), 64))
    np.testing.assert_array_equal(np.concatenate([parts[k] for k in sorted(parts)]), full)


def test_geodesic_on_a_non_manifold_mesh():
    """Three triangles on one edge: the heat method solver refuses it; edge paths take over."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], dtype=float)
    F = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    D = geodesic_distances(V, F, [2])[:, 0]
    np.testing.assert_allclose(D, [0.5, 0.5, 0.0, 1.0, 1.0], atol=1e-5)
    assert D.max() < 1.0
