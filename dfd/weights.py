"""Deformation weights from feature similarity (PIPELINE.md section 6).

For a vertex feature ``f(v)`` and a handle feature ``f(h)`` (unit vectors):

- distance form (default; the DFD code): ``w = clamp(1 - ||f(v) - f(h)||, 0, 1)``;
- cosine form (the DFD paper's text): ``w = clamp(f(v) . f(h) / (|f(v)| |f(h)|), 0, 1)``. For
  unit vectors ``||a - b||^2 = 2 - 2 a.b``, so both are decreasing functions of the same angle:
  the distance form reaches 0 at 60 degrees, the cosine form at 90 degrees.

Then, in this order:

- feature-space constraints: with fixed points of features ``f(c_k)`` (points that must not
  move), ``w <- max(0, w - max_k s(f(v), f(c_k)))`` where ``s`` is the same form; a vertex that
  looks like a fixed point loses its weight;
- locality: with ``d`` the geodesic distance from the handle normalized to [0, 1)
  (:func:`geodesic_distances`), ``w <- w (1 - d)^p``; ``p = 0`` disables it.

Binding is a matrix product plus elementwise work: for large meshes compute rows on demand
(:func:`weights_for_points`, :func:`iter_handle_weights`) rather than the full ``(n, h)`` matrix.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from scipy import sparse
from scipy.sparse import csgraph

from dfd.errors import DfdInputError
from dfd.mesh import check_mesh, weld

__all__ = [
    "handle_weights",
    "similarity",
    "iter_handle_weights",
    "weights_for_points",
    "geodesic_distances",
    "FORMS",
]

log = logging.getLogger(__name__)

FORMS = ("distance", "cosine")
#: Largest normalized geodesic distance, given to vertices the source cannot reach.
UNREACHABLE = float(np.nextafter(np.float32(1.0), np.float32(0.0)))


def _as_features(X, name):
    X = np.asarray(X, dtype=np.float32)
    if X.ndim != 2:
        raise DfdInputError(f"weights: {name} must be a 2D (rows, C) array, got shape {X.shape}")
    return X


def similarity(features, targets, *, form="distance"):
    """Similarity in [0, 1] of every feature row to every target row.

    Parameters
    ----------
    features : (n, C) float array
    targets : (t, C) float array
    form : {"distance", "cosine"}

    Returns
    -------
    (n, t) float32
    """
    if form not in FORMS:
        raise DfdInputError(f"weights: unknown form {form!r}; expected 'distance' or 'cosine'")
    A = torch.from_numpy(_as_features(features, "features"))
    B = torch.from_numpy(_as_features(targets, "targets"))
    if A.shape[1] != B.shape[1]:
        raise DfdInputError(f"weights: features have {A.shape[1]} channels but targets have {B.shape[1]}")
    G = A @ B.T  # (n, t)
    if form == "distance":
        na = A.square().sum(dim=1, keepdim=True)
        nb = B.square().sum(dim=1)
        # ||a - b|| = sqrt(|a|^2 + |b|^2 - 2 a.b), in place to keep one (n, t) buffer
        G.mul_(-2.0).add_(na).add_(nb).clamp_(min=0.0).sqrt_()
        G.neg_().add_(1.0).clamp_(min=0.0, max=1.0)
    else:
        na = A.norm(dim=1, keepdim=True).clamp_(min=1e-12)
        nb = B.norm(dim=1).clamp_(min=1e-12)
        G.div_(na).div_(nb).clamp_(min=0.0, max=1.0)
    return G.numpy()


def handle_weights(features, handle_features, *, form="distance", fixed=None, geodesic=None, p=0.0):
    """Per-handle weights of vertices from feature similarity.

    Parameters
    ----------
    features : (n, C) float array
        Field values at the vertices (unit rows).
    handle_features : (h, C) float array
        Field values at the handles (vertices or any points in space).
    form : {"distance", "cosine"}
        See the module docstring.
    fixed : (k, C) float array, optional
        Features of fixed points: the feature-space constraint subtracts each vertex's largest
        similarity to them, ``w <- max(0, w - max_k s(f(v), f(c_k)))``.
    geodesic : (n, h) float array in [0, 1), optional
        Normalized geodesic distance of each vertex to each handle (:func:`geodesic_distances`).
    p : float
        Locality exponent: ``w <- w (1 - d)^p``; 0 disables it. Needs ``geodesic`` when > 0.

    Returns
    -------
    W : (n, h) float32 in [0, 1]
        Rows do not sum to 1: :func:`dfd.deform.deform` gives the rest to a simulated control
        point that stays put.
    """
    W = similarity(features, handle_features, form=form)
    if fixed is not None and len(fixed):
        w_fixed = similarity(features, fixed, form=form).max(axis=1)
        np.subtract(W, w_fixed[:, None], out=W)
        np.maximum(W, 0.0, out=W)
    if p < 0:
        raise DfdInputError(f"weights: locality exponent p must be >= 0, got {p}")
    if p > 0:
        if geodesic is None:
            raise DfdInputError("weights: locality p > 0 needs the geodesic distances (geodesic=...)")
        D = np.asarray(geodesic, dtype=np.float32)
        if D.shape != W.shape:
            raise DfdInputError(f"weights: geodesic must be (n, h) = {W.shape}, got {D.shape}")
        W *= np.power(np.clip(1.0 - D, 0.0, 1.0), np.float32(p))
    return W


def iter_handle_weights(features, handle_features, *, chunk=65536, geodesic=None, **kwargs):
    """Weights row block by row block, for meshes whose ``(n, h)`` matrix should not be stored.

    Parameters
    ----------
    features : (n, C) float array
    handle_features : (h, C) float array
    chunk : int
        Rows per block.
    geodesic : (n, h) float array, optional
        Sliced per block.
    **kwargs
        ``form``, ``fixed``, ``p``: as :func:`handle_weights`.

    Yields
    ------
    start : int
        First row of the block.
    W : (b, h) float32
    """
    n = len(features)
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        g = None if geodesic is None else geodesic[start:stop]
        yield start, handle_weights(features[start:stop], handle_features, geodesic=g, **kwargs)


def weights_for_points(field, points, handle_features, **kwargs):
    """Weights of any points (a chunk of vertices, on demand) from a feature field.

    Parameters
    ----------
    field : dfd.field.FeatureField
    points : (b, 3) float array
        In the field's mesh coordinates.
    handle_features : (h, C) float array
        E.g. ``field.evaluate(V[handles])``.
    **kwargs
        ``form``, ``fixed``, ``geodesic`` (rows of these points), ``p``: as :func:`handle_weights`.

    Returns
    -------
    (b, h) float32
    """
    return handle_weights(field.evaluate(points), handle_features, **kwargs)


def _components(n, F):
    """Connected component label of each of ``n`` vertices, through the edges of ``F``."""
    i = np.concatenate([F[:, 0], F[:, 1], F[:, 2]])
    j = np.concatenate([F[:, 1], F[:, 2], F[:, 0]])
    A = sparse.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    return csgraph.connected_components(A, directed=False)[1]


def _edge_dijkstra(V, F, sources):
    """Exact shortest paths along mesh edges ``(len(sources), n)``: the fallback for meshes the
    heat method solver rejects (non-manifold)."""
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    length = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    A = sparse.coo_matrix((length, (E[:, 0], E[:, 1])), shape=(len(V), len(V))).tocsr()
    return csgraph.dijkstra(A, directed=False, indices=sources)


def geodesic_distances(V, F, sources, *, scale=None):
    """Geodesic distance of every vertex to each source vertex, normalized to [0, 1).

    Computed on the mesh welded by position (split glTF meshes would otherwise cut distances at
    every seam) with the heat method of potpourri3d (``MeshHeatMethodDistanceSolver``); a mesh the
    solver rejects (non-manifold) falls back to shortest paths along edges, with a warning.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    sources : (h,) int array
        Source vertex indices (handles).
    scale : float, optional
        Distance that maps to 1. Default: the largest finite distance found, times ``1 + 1e-6``,
        so that every value is below 1 and all handles share one scale.

    Returns
    -------
    D : (n, h) float32 in [0, 1)
        Vertices in another connected component than the source get the largest float32 below 1
        (locality then removes their weight).
    """
    V, F = check_mesh(V, F, stage="geodesic")
    sources = np.atleast_1d(np.asarray(sources, dtype=np.int64))
    if sources.size and (sources.min() < 0 or sources.max() >= len(V)):
        raise DfdInputError(f"geodesic: source vertices must lie in [0, {len(V)}), got {sources.tolist()}")
    Vw, index, Fw = weld(V, F)
    Fw = Fw[(Fw[:, 0] != Fw[:, 1]) & (Fw[:, 1] != Fw[:, 2]) & (Fw[:, 2] != Fw[:, 0])]
    used = np.unique(Fw)
    compact = np.full(len(Vw), -1, dtype=np.int64)
    compact[used] = np.arange(len(used))
    Vc, Fc = Vw[used], compact[Fw]
    src = compact[index[sources]]
    label = _components(len(Vc), Fc)
    Dc = np.full((len(src), len(Vc)), np.inf)
    live = src >= 0  # a source on a degenerate face only has no distances
    try:
        import potpourri3d as pp3d

        solver = pp3d.MeshHeatMethodDistanceSolver(Vc, Fc)
        for k in np.flatnonzero(live):
            Dc[k] = solver.compute_distance(int(src[k]))
    except (RuntimeError, ValueError) as exc:
        log.warning("geodesic: heat method failed (%s); using shortest paths along edges", exc)
        if live.any():
            Dc[live] = _edge_dijkstra(Vc, Fc, src[live])
    for k in np.flatnonzero(live):
        Dc[k, label != label[src[k]]] = np.inf
    Dc = np.maximum(Dc, 0.0)
    Dc[np.flatnonzero(live), src[live]] = 0.0
    finite = np.isfinite(Dc)
    if scale is None:
        scale = float(Dc[finite].max()) * (1.0 + 1e-6) if finite.any() else 1.0
        scale = scale if scale > 0 else 1.0
    out = np.full((len(V), len(sources)), UNREACHABLE, dtype=np.float32)
    rows = compact[index]  # (n,) compact vertex of each input vertex, -1 if on no valid face
    ok = rows >= 0
    Dn = np.where(finite, np.minimum(Dc / scale, UNREACHABLE), UNREACHABLE).astype(np.float32)
    out[ok] = Dn[:, rows[ok]].T
    return out
