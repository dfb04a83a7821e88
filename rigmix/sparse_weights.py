"""Skin weights as sparse ``(n, J)`` matrices: memory in the influences, not in vertices x joints.

A file stores each vertex's few influences (``JOINTS_n`` / ``WEIGHTS_n``); a dense ``(n, J)``
float64 matrix of them costs ``8 n J`` bytes, 1.9 GiB for 12,000 vertices on a 20,000-joint chain.
:func:`influence_matrix` keeps them as a CSR matrix (``O(n k)``), and :func:`dense_rows` /
:func:`row_blocks` give a computation that needs dense rows a block of them at a time, so its
peak memory is bounded by :data:`BLOCK_ENTRIES` whatever ``J``.

The values equal those of the dense matrix (:meth:`rigmix.character.Mesh.dense_weights`) bit for
bit: duplicate slots of a vertex summed in slot order, zero weights not stored, and any dense
computation run on :func:`dense_rows` blocks gives each row the same floats as on the whole
dense matrix.

The output's weights are held the same way, from retargeting to assembly. NumPy sums a dense row
pairwise, so the floats of a row's sum depend on where its zeros lie: :func:`row_sums` takes them
over dense row blocks, and :func:`positive_counts`, :func:`column_support` and :func:`set_rows`
(a band of rows computed densely, put back) need no dense matrix at all.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["BLOCK_ENTRIES", "column_support", "dense_rows", "from_dense", "influence_matrix", "positive_counts",
           "row_blocks", "row_sums", "set_rows"]

#: Entries of a dense block made at once (8 MiB of float64).
BLOCK_ENTRIES = 2**20


def influence_matrix(rows, joints, weights, shape) -> sp.csr_matrix:
    """The ``(n, J)`` CSR matrix of per-influence weights.

    Parameters
    ----------
    rows : (m,) int array
        The vertex (row) of each influence.
    joints : (m,) int array
        Its joint (column), in ``[0, J)``.
    weights : (m,) float array
        Its weight.
    shape : (int, int)
        ``(n, J)``.

    Returns
    -------
    scipy.sparse.csr_matrix
        float64, canonical (column indices sorted, no duplicates); influences of one vertex on
        one joint summed in the order given (as ``np.add.at`` on a dense matrix); zero sums
        not stored.
    """
    rows = np.asarray(rows, np.int64).ravel()
    joints = np.asarray(joints, np.int64).ravel()
    weights = np.asarray(weights, np.float64).ravel()
    order = np.lexsort((joints, rows))  # stable: duplicates keep their slot order
    r, j, w = rows[order], joints[order], weights[order]
    start = np.flatnonzero(np.r_[True, (r[1:] != r[:-1]) | (j[1:] != j[:-1])]) if len(r) else np.zeros(0, np.int64)
    total = np.add.reduceat(w, start) if len(r) else np.zeros(0)
    r, j = r[start], j[start]
    keep = total != 0.0
    W = sp.csr_matrix((total[keep], (r[keep], j[keep])), shape=shape)
    W.sort_indices()
    return W


def dense_rows(W, rows=None) -> np.ndarray:
    """Rows of a weight matrix as a dense float64 array.

    Parameters
    ----------
    W : (n, J) float array or scipy.sparse matrix
    rows : int array (any shape) or slice, optional
        Default: every row.

    Returns
    -------
    (len(rows), J) float64 array
        (``rows.shape + (J,)`` for an integer array.)
    """
    if not sp.issparse(W):
        W = np.asarray(W, np.float64)
        return W if rows is None else W[rows]
    if rows is None:
        return W.toarray()
    if isinstance(rows, slice):
        return W[rows].toarray()
    rows = np.asarray(rows, np.int64)
    return W[rows.ravel()].toarray().reshape(rows.shape + (W.shape[1],))


def row_blocks(n: int, num_cols: int, entries: int = BLOCK_ENTRIES):
    """Slices covering ``range(n)``, each of at most ``max(1, entries // num_cols)`` rows.

    Yields
    ------
    slice
    """
    step = max(1, int(entries) // max(int(num_cols), 1))
    for start in range(0, int(n), step):
        yield slice(start, min(start + step, int(n)))


def from_dense(X) -> sp.csr_matrix:
    """A dense ``(n, J)`` weight block as a canonical CSR matrix (zeros not stored, indices sorted)."""
    W = sp.csr_matrix(np.asarray(X, np.float64))
    W.sort_indices()
    return W


def row_sums(W) -> np.ndarray:
    """Each row's sum, ``(n,)`` float64: the same floats as ``W.sum(axis=1)`` of the dense matrix.

    NumPy sums a dense row pairwise, so the floats depend on where the zeros lie; a sparse matrix
    is summed over dense blocks of rows (:func:`row_blocks`) to give each row exactly those.
    """
    if not sp.issparse(W):
        return np.asarray(W, np.float64).sum(axis=1)
    n, J = W.shape
    out = np.zeros(n)
    for rows in row_blocks(n, J):
        out[rows] = W[rows].toarray().sum(axis=1)
    return out


def positive_counts(W) -> np.ndarray:
    """Entries above zero in each row, ``(n,)`` int64 (``np.count_nonzero(W > 0, axis=1)``)."""
    if not sp.issparse(W):
        return np.count_nonzero(np.asarray(W) > 0, axis=1)
    W = sp.csr_matrix(W)
    W.sum_duplicates()
    row = np.repeat(np.arange(W.shape[0]), np.diff(W.indptr))
    return np.bincount(row[W.data > 0], minlength=W.shape[0]).astype(np.int64)


def column_support(W) -> np.ndarray:
    """Columns with an entry above zero in some row, ``(J,)`` bool (``(W > 0).any(axis=0)``)."""
    if not sp.issparse(W):
        return (np.asarray(W) > 0).any(axis=0)
    W = sp.csr_matrix(W)
    W.sum_duplicates()
    out = np.zeros(W.shape[1], bool)
    out[W.indices[W.data > 0]] = True
    return out


def set_rows(W, rows, block) -> sp.csr_matrix:
    """``W`` with ``rows`` replaced by the dense ``block``, as a new canonical CSR matrix.

    Parameters
    ----------
    W : (n, J) scipy.sparse matrix
    rows : (q,) int array
        Distinct rows.
    block : (q, J) float array or scipy.sparse matrix
        Their new values (zeros not stored).
    """
    W = sp.csr_matrix(W)
    rows = np.asarray(rows, np.int64).ravel()
    n = W.shape[0]
    pick = np.arange(n)
    pick[rows] = n + np.arange(len(rows))
    if sp.issparse(block):
        block = sp.csr_matrix(block)
    else:
        block = from_dense(np.asarray(block, np.float64).reshape(len(rows), W.shape[1]))
    out = sp.vstack([W, block], format="csr")[pick]
    out.sort_indices()
    return out
