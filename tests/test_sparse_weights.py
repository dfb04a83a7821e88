"""Skin weights held per influence give the dense computations' floats bit for bit.

The output's weights are CSR matrices from retargeting to assembly (:mod:`rigmix.sparse_weights`).
NumPy sums a dense row pairwise, so a row's sum depends on where its zeros lie; the row-wise
reductions of a sparse matrix are taken over dense blocks of rows to give exactly those floats, and
the composed files stay byte-identical to what dense weights give. Checked here on a real
character's weights spread over thousands of joints (as on a long chain, where the zeros between
the influences decide the summation order).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from conftest import asset

from rigmix.fusion.inputs import fusion_input
from rigmix.io import load_character
from rigmix.operations.positioning import cross_section, part_weights, rest_world_mesh
from rigmix.sparse_weights import column_support, positive_counts, row_sums, set_rows
from rigmix.weights.retarget import retarget_weights, to_influences

SPREAD = 5000


def _spread_weights():
    """CesiumMan's weights ``(n, 19)`` with its joints placed among :data:`SPREAD` columns, CSR."""
    ch = load_character(asset("CesiumMan"))
    W = fusion_input(ch, np.ones(ch.skeleton.num_joints, bool)).W
    cols = np.random.default_rng(0).choice(SPREAD, W.shape[1], replace=False)
    S = sp.csr_matrix((np.ones(W.shape[1]), (np.arange(W.shape[1]), cols)), shape=(W.shape[1], SPREAD))
    return sp.csr_matrix(W @ S)


def test_row_reductions_equal_the_dense_ones_bit_for_bit():
    W = _spread_weights()
    D = W.toarray()
    assert row_sums(W).tobytes() == D.sum(axis=1).tobytes()
    assert np.array_equal(positive_counts(W), np.count_nonzero(D > 0, axis=1))
    assert np.array_equal(column_support(W), (D > 0).any(axis=0))
    J, w = to_influences(W, 4)
    Jd, wd = to_influences(D, 4)
    assert J.tobytes() == Jd.tobytes() and w.tobytes() == wd.tobytes()
    rows = np.arange(0, W.shape[0], 7)
    new = np.roll(D[rows], 3, axis=1)
    D[rows] = new
    assert set_rows(W, rows, new).toarray().tobytes() == D.tobytes()


def test_retargeted_weights_equal_the_dense_product_bit_for_bit():
    """Many input joints onto one output joint, some unmapped: the renormalized rows are those of
    the dense product."""
    W = _spread_weights()
    rng = np.random.default_rng(1)
    target = rng.integers(0, 800, SPREAD)
    target[rng.random(SPREAD) < 0.3] = -1
    conf = rng.random(SPREAD)
    Wr, c = retarget_weights(W, target, 800, confidence=conf)
    assert sp.issparse(Wr)
    ok = target >= 0
    B = np.zeros((SPREAD, 800))
    B[np.flatnonzero(ok), target[ok]] = 1.0
    D = np.asarray((sp.csr_matrix(W) @ sp.csr_matrix(B)).todense())
    s = D.sum(axis=1)
    off = (s > 0) & (np.abs(s - 1.0) > 1e-12)
    D[off] /= s[off, None]
    assert Wr.toarray().tobytes() == D.tobytes()
    np.testing.assert_allclose(c, np.clip(W.toarray() @ conf, 0.0, 1.0), rtol=0, atol=1e-12)
    # a row's confidence is the same float whichever block of rows it is computed in (a BLAS
    # product's sum depends on the row's place in the block and on the thread count)
    for start in (1, 5, 3333):
        assert retarget_weights(W[start:], target, 800, confidence=conf)[1].tobytes() == c[start:].tobytes()


def test_positioning_measures_on_the_influences_equal_the_dense_ones():
    ch = load_character(asset("Fox"))
    V, W = rest_world_mesh(ch)
    assert sp.issparse(W)
    D = np.concatenate([m.dense_weights(ch.skeleton.num_joints) for m in ch.meshes])
    assert W.toarray().tobytes() == D.tobytes()
    for j in range(ch.skeleton.num_joints):
        sub = ch.skeleton.subtree(j)
        assert part_weights(W, sub).tobytes() == part_weights(D, sub).tobytes()
        assert cross_section(V, W, V[0], j) == cross_section(V, D, V[0], j)
