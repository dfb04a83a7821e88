"""Deformation by linear blending of handle affine maps (PIPELINE.md section 6).

Each vertex blends its handles' affine maps ``A_h p + t_h`` by its weights, plus a simulated
control point that never moves and carries ``max(0, 1 - sum_h w_h)`` of the identity; the
weights are then divided by their total ``max(1, sum_h w_h)``:

    v' = v + sum_h w_h ((A_h - I) v + t_h) / max(1, sum_h w_h)

Written as a displacement, zero motion reproduces the mesh bit for bit. The cost is one pass
over the dense weights, in one matrix product with a column per used entry of the maps: for 1M
vertices and 100 handles the float32 weights are 400 MB, so the product is bound by memory
bandwidth (``benchmarks/dfd_bench.py``).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from dfd.errors import DfdInputError

__all__ = ["deform", "deform_reference", "translations"]


#: Rows of a block of :func:`deform` (its (block, k + 1) product stays in cache).
ROWS_PER_BLOCK = 65536


def _check(V, W, transforms):
    V = np.asarray(V)
    W = np.asarray(W)
    T = np.asarray(transforms, dtype=np.float64)
    if T.ndim == 3 and T.shape[1:] == (4, 4):
        T = T[:, :3, :]
    if V.ndim != 2 or V.shape[1] != 3:
        raise DfdInputError(f"deform: V must be (n, 3), got {V.shape}")
    if T.ndim != 3 or T.shape[1:] != (3, 4):
        raise DfdInputError(f"deform: transforms must be (h, 3, 4) or (h, 4, 4), got {T.shape}")
    if W.shape != (len(V), len(T)):
        raise DfdInputError(f"deform: W must be (n, h) = ({len(V)}, {len(T)}), got {W.shape}")
    return V, W, T


def deform(V, W, transforms):
    """Deform vertices by blending handle affine maps with a simulated control point.

    Parameters
    ----------
    V : (n, 3) float array
        Rest positions, mesh coordinates.
    W : (n, h) float array
        Handle weights, non-negative (e.g. :func:`dfd.weights.handle_weights`); rows may sum to
        less than 1 (the simulated control point takes the rest) or more (then they are
        normalized).
    transforms : (h, 3, 4) or (h, 4, 4) float array
        Affine map of each handle, acting on column vectors: ``p' = T[:, :3] @ p + T[:, 3]``.

    Returns
    -------
    (n, 3) array of ``V``'s floating dtype
        Deformed positions; exactly ``V`` when every transform is the identity.
    """
    V, W, T = _check(V, W, transforms)
    out_dtype = V.dtype if np.issubdtype(V.dtype, np.floating) else np.float64
    work = np.float32 if W.dtype == np.float32 else np.float64
    D = T.copy()
    D[:, :, :3] -= np.eye(3)  # displacement maps: zero for a handle that does not move
    D = D.reshape(len(T), 12)
    # Only the entries of (A - I | t) that some handle uses cost a column of the product
    # (translations: 3 of 12); one more column gives the weight sums.
    used = np.flatnonzero(np.any(D != 0.0, axis=0))
    Dm = np.concatenate([D[:, used], np.ones((len(T), 1))], axis=1).astype(work)  # (h, k + 1)
    rows, cols = np.divmod(used, 4)  # row r, column c of the blended (A - I | t)
    entries = None if np.array_equal(rows, np.arange(3)) and np.all(cols == 3) else list(zip(rows, cols))
    out = np.empty(V.shape, dtype=out_dtype)
    # Each row depends on its own row of W only, so blocks of rows run on threads (numpy and
    # BLAS release the GIL): the result is the same bit for bit whatever the split, and the
    # memory-bound read of W uses every core even where BLAS runs one thread.
    starts = range(0, len(V), ROWS_PER_BLOCK)
    workers = min(len(starts), os.cpu_count() or 1)
    if workers <= 1:
        _deform_rows(V, W, Dm, entries, work, out, 0, len(V))
    else:
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(lambda a: _deform_rows(V, W, Dm, entries, work, out, a, a + ROWS_PER_BLOCK), starts))
    return out


def _deform_rows(V, W, Dm, entries, work, out, a, b):
    """Write ``out[a:b]``: rows ``a:b`` of :func:`deform`.

    ``Dm`` ``(h, k + 1)``: the used entries of the handles' ``(A - I | t)`` and a column of ones;
    ``entries``: the (row, column) in the (3, 4) map of each of the ``k`` used entries, or None
    when they are the three translations in order."""
    R = W[a:b].astype(work, copy=False) @ Dm  # (rows, k + 1): blended entries, then the weight sum
    total = np.maximum(R[:, -1:], 1.0)  # the control point takes max(0, 1 - sum w)
    if entries is None:
        disp = R[:, :3]  # translations only: the blended offsets themselves
    else:
        Vw = V[a:b].astype(work, copy=False)
        disp = np.zeros((len(R), 3), dtype=work)
        for j, (r, c) in enumerate(entries):
            disp[:, r] += R[:, j] if c == 3 else R[:, j] * Vw[:, c]
    disp /= total
    np.add(V[a:b], disp, out=out[a:b], casting="unsafe")


def deform_reference(V, W, transforms):
    """Slow, literal version of :func:`deform` (per-handle loop), kept for tests."""
    V, W, T = _check(V, W, transforms)
    V = V.astype(np.float64)
    W = W.astype(np.float64)
    control = np.maximum(0.0, 1.0 - W.sum(axis=1))
    out = control[:, None] * V
    for h in range(len(T)):
        out += W[:, h : h + 1] * (V @ T[h, :, :3].T + T[h, :, 3])
    return out / (W.sum(axis=1) + control)[:, None]


def translations(offsets):
    """Pure translation maps ``(h, 3, 4)`` from offsets ``(h, 3)``."""
    offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 3)
    T = np.zeros((len(offsets), 3, 4))
    T[:, :, :3] = np.eye(3)
    T[:, :, 3] = offsets
    return T
