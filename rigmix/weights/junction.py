"""Junction operators of the weights stage: matching junction vertices to their inputs, the
harmonic blend factors, and the continuation of an input's far, jumping weights.

Used by :func:`rigmix.weights.blend_weights` (:func:`rigmix.weights.blend.blend_junction` and
:func:`rigmix.weights.blend.match_junction_rows`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from dfd.mesh import face_normals, welded_graph

from ..fusion.inputs import check_dense_weights
from ..geometry import neighbour_roughness

__all__ = ["match_junction", "harmonic_blend_factors", "continue_far_parts"]


def match_junction(JV, JN, sources, inputs_V, inputs_F, *, diagonal, match_distance=0.05, match_angle=30.0,
                   on_surface=0.0):
    """Robust-transfer matching of junction vertices (Abdrashitov et al. 2023).

    Parameters
    ----------
    JV, JN : (q, 3) float arrays
        Junction vertex positions and unit normals.
    sources : sequence of dict
        ``FusedSurface.junction_sources`` (closest point face and distance per input).
    inputs_V, inputs_F : sequences of (n_i, 3) and (m_i, 3) arrays
    diagonal : float
        Bounding-box diagonal of the fused surface.
    match_distance : float
        Fraction of ``diagonal``.
    match_angle : float
        Degrees.
    on_surface : float
        Fraction of ``diagonal``: a vertex this close to the closest (present) input point lies
        on that input's surface, and is matched whatever the normals (the remeshed isosurface's
        normals in thin parts and creases differ from the input's by more than any angle
        tolerance while the point and its weights are the input's own). 0: off.

    Returns
    -------
    matched : (q,) bool
        The closest (present) input point is within ``on_surface``, or within the distance with
        its face normal within the angle (either orientation of the source face is accepted only
        if it agrees: no flip).
    """
    q = len(JV)
    matched = np.zeros(q, bool)
    if q == 0:
        return matched
    cos_max = np.cos(np.radians(match_angle))
    D = np.stack([s["distance"] for s in sources], axis=1)
    P = np.stack([s["presence"] for s in sources], axis=1)
    # the input that shapes the vertex: the closest among those present there
    score = np.where(P > 0.5, D, np.inf)
    score[~np.isfinite(score.min(axis=1))] = D[~np.isfinite(score.min(axis=1))]
    best = np.argmin(score, axis=1)
    for i, s in enumerate(sources):
        rows = np.flatnonzero(best == i)
        if not len(rows):
            continue
        Vx, Fx = np.asarray(inputs_V[i], np.float64), np.asarray(inputs_F[i], np.int64)
        T = Fx[np.asarray(s["face"], np.int64)[rows]]
        cos = np.einsum("qk,qk->q", face_normals(Vx, T), JN[rows])
        d = np.asarray(s["distance"])[rows]
        on = (d <= on_surface * diagonal) if on_surface > 0 else False
        matched[rows] = ((d <= match_distance * diagonal) & (cos >= cos_max)) | on
    return matched


def harmonic_blend_factors(V, F, T, free, *, graph=None):
    """Blend factors that vary harmonically across the junction, fixed on the preserved parts.

    Solves the graph Laplace equation ``L t = 0`` on the welded mesh for the ``free`` rows, the
    other rows fixed (a welded vertex is fixed when any of its split vertices is). Each free
    vertex then mixes the inputs in proportion to how close, along the surface, it is to each
    input's preserved part: the transition spans the whole junction instead of jumping where the
    closest input changes (the paper's ``presence / distance`` factor).

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    T : (n, I) float array
        Blend factors per input: one-hot of the source input on fixed rows; on free rows the
        value kept where a connected component of free vertices touches no fixed vertex.
    free : (n,) bool array
    graph : tuple, optional
        :func:`dfd.mesh.welded_graph` of ``(V, F)``, when the caller has it.

    Returns
    -------
    T : (n, I) float64
        Free rows non-negative and summing to 1 (a convex combination of the fixed rows); fixed
        rows unchanged.
    """
    T = np.asarray(T, np.float64).copy()
    free = np.asarray(free, bool)
    if not free.any() or free.all():
        return T
    return _harmonic_rows(V, F, T, ~free, free, graph=graph)


def _harmonic_rows(V, F, X, fixed, free, graph=None):
    """Rows ``free`` of ``X`` ``(n, c)`` harmonic (graph Laplace equation on the welded mesh
    restricted to the ``fixed`` and ``free`` rows), the ``fixed`` rows as boundary values (a
    welded vertex is fixed when any of its split vertices is, with their mean). Solved rows are
    clipped at 0 and normalized to sum 1 (a convex combination of the boundary rows); a free
    row whose component of the subgraph has no fixed row keeps its value. ``graph``: the
    :func:`dfd.mesh.welded_graph` of ``(V, F)`` when the caller has it."""
    X = np.asarray(X, np.float64).copy()
    fixed, free = np.asarray(fixed, bool), np.asarray(free, bool) & ~np.asarray(fixed, bool)
    Vw, index, G = graph if graph is not None else welded_graph(V, F)
    k = len(Vw)
    fixed_w = np.zeros(k, bool)
    fixed_w[index[fixed]] = True
    free_w = np.zeros(k, bool)
    free_w[index[free]] = True
    free_w &= ~fixed_w
    Xw = np.zeros((k, X.shape[1]))
    np.add.at(Xw, index[fixed], X[fixed])
    Xw[fixed_w] /= np.bincount(index[fixed], minlength=k)[fixed_w, None]
    inside = np.flatnonzero(fixed_w | free_w)
    A = (G[inside][:, inside] > 0).astype(np.float64)
    L = (sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A).tocsr()
    _, comp = connected_components(A, directed=False)
    anchored = np.zeros(comp.max() + 1 if len(comp) else 0, bool)
    anchored[comp[fixed_w[inside]]] = True
    s = np.flatnonzero(free_w[inside] & anchored[comp])  # a component without a fixed row is singular
    if len(s):
        kn = np.flatnonzero(fixed_w[inside])
        x = splu(L[s][:, s].tocsc()).solve(np.ascontiguousarray(-(L[s][:, kn] @ Xw[inside[kn]])))
        x = np.clip(x, 0.0, None)
        x /= np.maximum(x.sum(axis=1, keepdims=True), 1e-300)
        solved = np.zeros(k, bool)
        solved[inside[s]] = True
        rows = free & solved[index]
        X[rows] = x[np.searchsorted(inside[s], index[rows])]
    return X


def continue_far_parts(V, F, parts, distances, junction, known, *, near, jump=0.2, graph=None):
    """Each input's closest-point weights, continued harmonically where they jump far from it.

    At a junction vertex farther than ``near`` from an input, that input's closest point is a
    projection across space, and it jumps between the two sides of the input's medial axis
    from one vertex to the next (a fused armpit: the closest point on the torso input
    alternates between chest and shoulder stump). Blended by harmonic factors, which still give
    the far input much of the vertex, the jumps stripe the seam: neighbouring vertices alternate
    between two weight rows (beast_arms example: half-L1 roughness 0.29 against 0.14 on the
    inputs' own painting). There, and only there (far from the input and the input's rows among
    the junction neighbours differing by more than ``jump``, half L1 from their mean), the input's
    weights are continued harmonically from the junction vertices near it, where they are its
    own painting, and from its preserved vertices.

    Parameters
    ----------
    V : (n, 3) float array
        The fused surface.
    F : (m, 3) int array
    parts : sequence of (q, J) float arrays
        Per input, the closest-point weights of the ``q`` junction vertices (in the order of
        ``np.flatnonzero(junction)``).
    distances : sequence of (q,) float arrays
        Per input, the distance from each junction vertex to its closest point (units of ``V``).
    junction : (n,) bool array
    known : sequence of ``(rows, weights)``
        Per input, the surface rows it preserves ``(r,)`` int and their weights ``(r, J)``
        (float array or scipy.sparse matrix).
    near : float
        Units of ``V``.
    jump : float
    graph : tuple, optional
        :func:`dfd.mesh.welded_graph` of ``(V, F)``, when the caller has it.

    Returns
    -------
    list of (q, J) float64 arrays
        ``parts`` with the jumping far rows replaced; rows non-negative, summing to 1.

    Raises
    ------
    InputError
        The continuation solves over the whole surface, densely: ``(n, J)`` past
        :data:`rigmix.fusion.inputs.MAX_DENSE_WEIGHT_ENTRIES` entries.
    """
    junction = np.asarray(junction, bool)
    jrows = np.flatnonzero(junction)
    out = []
    for P, d, (rows, K) in zip(parts, distances, known):
        P = np.asarray(P, np.float64)
        far = np.asarray(d) > near
        if far.any() and graph is None:
            graph = welded_graph(V, F)  # built once: at a million faces it is the cost
        cont = far & (_junction_roughness(graph, P, jrows) > jump) if far.any() else far
        if not cont.any():
            out.append(P.copy())
            continue
        check_dense_weights(len(V), P.shape[1], "weights: the junction's harmonic continuation (dense over the "
                            "fused surface)")
        X = np.zeros((len(V), P.shape[1]))
        if sp.issparse(K):  # scattered per influence: no dense copy of the preserved rows
            K = sp.coo_matrix(K)
            K.sum_duplicates()
            X[np.asarray(rows)[K.row], K.col] = K.data
        else:
            X[rows] = K
        X[jrows] = P
        fixed = np.zeros(len(V), bool)
        fixed[rows] = True
        fixed[jrows[~cont]] = True
        free = np.zeros(len(V), bool)
        free[jrows[cont]] = True
        out.append(_harmonic_rows(V, F, X, fixed, free, graph=graph)[jrows])
    return out


def _junction_roughness(graph, P, jrows):
    """Half L1 from each junction row of ``P`` ``(q, J)`` to the mean of its junction neighbours'
    (on the welded ``graph``; 0 for a row without one)."""
    Vw, index, G = graph
    ids, pos = np.unique(index[jrows], return_inverse=True)
    Pw = np.zeros((len(ids), P.shape[1]))
    np.add.at(Pw, pos, P)
    Pw /= np.bincount(pos, minlength=len(ids))[:, None]
    return neighbour_roughness(G[ids][:, ids], Pw)[0][pos]
