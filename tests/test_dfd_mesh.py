"""dfd.mesh's shared operators: weld, welded_graph, smooth (on small cases computed by hand)."""

import numpy as np

from dfd.mesh import smooth, weld, welded_graph


def _split_quad():
    """Two triangles of the unit square, split at the diagonal (6 vertices, 4 positions)."""
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    F = np.array([[0, 1, 2], [3, 4, 5]])
    return V, F


def test_weld_keeps_first_appearance_order_and_face_count():
    V, F = _split_quad()
    Vw, index, Fw = weld(V, F)
    np.testing.assert_array_equal(index, [0, 1, 2, 0, 2, 3])
    np.testing.assert_array_equal(Vw[index], V)
    np.testing.assert_array_equal(Fw, index[F])
    Vt, it = weld(V + np.array([1e-9, 0, 0]) * (np.arange(6) % 2)[:, None], tol=1e-6)
    assert len(Vt) == 4 and len(it) == 6
    Ve, ie = weld(np.zeros((0, 3)))
    assert Ve.shape == (0, 3) and ie.shape == (0,)


def test_welded_graph_lengths_and_adjacency_agree():
    V, F = _split_quad()
    _, index, G = welded_graph(V, F)
    _, index_a, A = welded_graph(V, F, lengths=False)
    np.testing.assert_array_equal(index, index_a)
    assert (G != G.T).nnz == 0 and (A != A.T).nnz == 0
    np.testing.assert_array_equal((G > 0).toarray(), A.toarray() > 0)
    assert A.nnz == 10  # the square's 4 sides and its diagonal, both ways
    np.testing.assert_allclose(G[0, 2], np.sqrt(2), atol=1e-9)


def test_smooth_alpha_is_the_fraction_moved_to_the_mean():
    A = welded_graph(*_split_quad(), lengths=False)[2]
    X = np.array([0.0, 1.0, 2.0, 3.0])
    free = np.array([True, False, False, False])
    np.testing.assert_array_equal(smooth(A, X, free, iterations=1, alpha=0.0), X)
    mean = (1.0 + 2.0 + 3.0) / 3
    np.testing.assert_allclose(smooth(A, X, free, iterations=1, alpha=1.0), [mean, 1, 2, 3])
    np.testing.assert_allclose(smooth(A, X[:, None], free, iterations=1, alpha=0.25)[:, 0], [0.5, 1, 2, 3])
    np.testing.assert_array_equal(X, [0.0, 1.0, 2.0, 3.0])  # the input is not modified
