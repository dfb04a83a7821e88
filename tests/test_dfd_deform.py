"""dfd.deform: linear blending with the simulated control point."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import asset
from scipy.spatial.transform import Rotation

from dfd.deform import deform, deform_reference, translations
from dfd.io import read_mesh


@pytest.fixture(scope="module", params=["CesiumMan", "Horse"])
def mesh(request):
    return read_mesh(asset(request.param))


def _weights(n, h, seed, dtype=np.float32):
    rng = np.random.default_rng(seed)
    W = rng.uniform(0.0, 0.6, size=(n, h))
    W[rng.random((n, h)) < 0.5] = 0.0  # many rows sum below 1, some above
    return W.astype(dtype)


def test_zero_motion_reproduces_the_mesh_exactly(mesh):
    for dtype in (np.float32, np.float64):
        W = _weights(len(mesh.V), 5, 0, dtype)
        assert np.array_equal(deform(mesh.V, W, translations(np.zeros((5, 3)))), mesh.V)


def test_matches_reference(mesh):
    rng = np.random.default_rng(3)
    T = np.concatenate([Rotation.random(4, random_state=4).as_matrix(), rng.normal(size=(4, 3, 1))], axis=2)
    T[:, :, :3] *= rng.uniform(0.5, 1.5, size=(4, 1, 1))  # affine, not only rigid
    W = _weights(len(mesh.V), 4, 5, np.float64)
    np.testing.assert_allclose(deform(mesh.V, W, T), deform_reference(mesh.V, W, T), atol=1e-9)
    W32 = W.astype(np.float32)
    scale = np.abs(mesh.V).max() + 1.0
    np.testing.assert_allclose(deform(mesh.V, W32, T), deform_reference(mesh.V, W32, T), atol=1e-5 * scale)


def test_one_rigid_motion_everywhere(mesh):
    """Rows that sum to at least 1 leave the control point nothing: a common rigid map is exact."""
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    t = np.array([0.3, -1.0, 2.0])
    T = np.broadcast_to(np.concatenate([R, t[:, None]], axis=1), (3, 3, 4))
    W = _weights(len(mesh.V), 3, 6, np.float64) + 0.4  # every row sums to >= 1.2
    np.testing.assert_allclose(deform(mesh.V, W, T), mesh.V @ R.T + t, atol=1e-9)


def test_control_point_holds_unweighted_vertices(mesh):
    W = _weights(len(mesh.V), 2, 7)
    W[:10] = 0.0
    W[10:20] = [0.25, 0.0]
    out = deform(mesh.V, W, translations([[1.0, 0.0, 0.0], [0.0, 5.0, 0.0]]))
    np.testing.assert_array_equal(out[:10], mesh.V[:10])
    # a quarter of the first handle's motion, three quarters held by the control point
    np.testing.assert_allclose(out[10:20], mesh.V[10:20] + [0.25, 0.0, 0.0], atol=1e-6)


def test_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match=r"\(n, h\)"):
        deform(np.zeros((4, 3)), np.zeros((4, 2)), translations(np.zeros((3, 3))))


def test_blocks_of_rows_give_the_same_result_bit_for_bit():
    """Past one block of rows, deform runs blocks on threads: every row comes out as it does
    when its block is deformed alone, and as the literal per-handle reference (to rounding)."""
    import dfd.deform as module

    rng = np.random.default_rng(3)
    n = 2 * module.ROWS_PER_BLOCK + 1234  # three blocks, the last one short
    V = rng.normal(size=(n, 3))
    W = rng.random((n, 7), dtype=np.float32)
    T = rng.normal(scale=0.2, size=(7, 3, 4))
    T[:, :, :3] += np.eye(3)
    whole = deform(V, W, T)
    b = module.ROWS_PER_BLOCK
    for a in (0, b, 2 * b):
        np.testing.assert_array_equal(whole[a:a + b], deform(V[a:a + b], W[a:a + b], T))
    np.testing.assert_allclose(whole, deform_reference(V, W, T), atol=1e-5)
    np.testing.assert_array_equal(deform(V, W, translations(np.zeros((7, 3)))), V)
