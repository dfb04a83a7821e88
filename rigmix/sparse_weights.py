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
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["BLOCK_ENTRIES", "dense_rows", "influence_matrix", "row_blocks"]

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
