"""W_R: the skinning weights of a composed character (PIPELINE.md section 4).

:func:`blend_weights` is the weight stage of :func:`rigmix.pipeline.compose`:

1. retarget each input's weights through its bone map (:func:`retarget_weights`: weights of
   input joints mapped to the same output joint are summed);
2. preserved vertices (copied from an input by the fusion) copy their retargeted row exactly;
3. junction vertices (made by the fusion) by one of three methods, all kept and compared by
   ``benchmarks/self_composition.py``:

``nearest``
    the paper's rule: the retargeted weights at the closest point of each input, interpolated
    by the blend factor (presence at that point, over distance).
``inpaint``
    the Robust Skin Weights Transfer anchor (Abdrashitov et al. 2023): a junction vertex is
    *matched* when its closest input point lies within ``match_distance`` x the bounding-box
    diagonal and the normals differ by at most ``match_angle`` degrees; matched vertices take
    the ``nearest`` weights, the others are inpainted (squared Laplacian, matched and
    preserved vertices fixed, smoothing) by :func:`rigmix.weights.fill_weights`, per connected
    component and never singular.
``dfd`` (default)
    the inputs' closest-point weights blended by *harmonic blend factors*
    (:func:`harmonic_blend_factors`: each junction vertex mixes the inputs by how close it is,
    along the surface, to each input's preserved part, so the transition spans the junction
    instead of jumping where the closest input changes, while each input's own weight profile,
    the artist's painting, is kept); matched as for ``inpaint`` but with a 90 degree normal
    tolerance (see ``match_angle``), and whatever the normals on an input's surface (within 0.5%
    of the diagonal, ``match_on_surface``); the rest (far or low-confidence vertices) filled by
    ``fill_weights(method="dfd")`` (prior borrowed from similar known parts, inpainting energy
    as regularizer) with *geodesic locality*: a joint keeps its weight on an unknown vertex
    only if the joint drives a known vertex (or, by the trusted mirror prior, a filled one)
    within a geodesic radius of it, so weights never leak to a look-alike part elsewhere (the
    other hand); a joint that deforms the inputs but no known vertex of the surface (its whole
    surface is filled: a head inside the junction band) keeps what the fill gives it.
    The DFD feature field of the fused surface is distilled (:data:`FIELD_DISTILL`, a few
    seconds on two cores) and decides how far the mirror prior is trusted: a vertex borrows its
    mirror point's weights only where the two points look alike. ``feature_field=False`` (config
    ``[weights] feature_field = false``, CLI ``--no-feature-field``) skips it: the prior is then
    trusted by the reflection distance alone.

Junction vertices whose mapping confidence (the confidence of the joints weighting their
closest input points) is below ``min_confidence`` are never matched: their weights are filled.
Every row of the result is non-negative, has at most ``max_influences`` non-zeros and sums to 1.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from dfd.mesh import face_normals, vertex_normals

from ..errors import InputError, NumericalError
from ..geometry import bounding_box_diagonal, neighbour_roughness, weld
from .mirror import feature_field as distill_feature_field
from .params import WeightParams
from .fill import fill_weights
from .mesh import sparsify
from .locality import geodesic_locality, welded_graph

__all__ = ["SkinWeights", "WEIGHT_METHODS", "BLEND_FACTORS", "ON_SURFACE", "JUNCTION_SMOOTHING", "FIELD_DISTILL",
           "retarget_weights", "closest_point_weights", "harmonic_blend_factors", "continue_far_parts",
           "match_junction", "geodesic_locality", "smooth_rows", "blend_weights", "to_influences"]

log = logging.getLogger(__name__)

WEIGHT_METHODS = ("nearest", "inpaint", "dfd")
#: How the inputs' closest-point weights are blended at a junction vertex (``blend_weights``).
BLEND_FACTORS = ("paper", "harmonic")

#: Distance from an input, as a fraction of the bounding-box diagonal, within which a junction
#: vertex lies on the input's surface (the fusion's own fidelity target): ``dfd`` matches it
#: whatever the normals (``match_on_surface``), and the harmonic blend reads the input's weights
#: there as its own painting (:func:`continue_far_parts`).
ON_SURFACE = 0.005

#: Post-smoothing iterations of the ``dfd`` fill on a junction (``fill_weights``' ``iterations``:
#: the robust transfer paper's 10, on the rows no prior decides). A junction band is the fusion's
#: isosurface, meshed at the voxel size, and there the smoothing removes isolated wrong rows:
#: hidden self-compositions, mean junction weight error 0.203 -> 0.198, mean skinned error
#: 2.78% -> 2.51% of the diagonal, Knight shoulder 8.1% -> 3.6%. On an artist's coarser mesh it
#: blurs the painting instead (band fill benchmark: 0.130 -> 0.158), so ``fill_weights``' own
#: default is 0.
JUNCTION_SMOOTHING = 10

#: Distillation settings of the feature field of ``dfd`` (:func:`dfd.distill.distill`): the
#: prototype's 24 views at 112 px instead of 224 (a quarter of the pixels) and 300 Adam steps of
#: 1024 pixels, the same ~7 passes over the covered pixels as the distiller's defaults (300 steps
#: of 4096 at 224 px). Measured on the Horse+Knight centaur's fused surface (19k welded vertices,
#: 2 CPU cores, busy machine): 4.5 to 7.6 s against 23 to 30 s with the distiller's defaults,
#: which would take the whole composition past the SkinMixer paper's 12 s average; with these
#: settings ``rigmix compose`` of the centaur takes 9.0 to 10.4 s (2.9 to 3.1 s without the
#: field). ``distill_options`` overrides them.
FIELD_DISTILL = {"n_views": 24, "resolution": 112, "steps": 300, "batch_size": 1024}


@dataclass(frozen=True)
class SkinWeights:
    """The weights of the fused surface.

    Attributes
    ----------
    W : (N, J_R) float64
        Dense weights on the output joints; rows non-negative, at most ``max_influences``
        non-zeros, summing to 1.
    junction : (N,) bool
        Vertices whose weights were computed (``FusedSurface.junction_vertices``).
    matched : (N,) bool
        Junction vertices whose weights were transferred (known to the fill).
    method : str
    report : dict
        ``method``, ``blend`` (the blend factors), ``max_influences``, ``min_sum``, ``max_sum``, ``junction_vertices``,
        ``matched_vertices``, ``low_confidence_vertices``, ``seam_smoothed_vertices``,
        ``seam_welded_vertices`` (junction rows given their seam partner's weights,
        :func:`weld_consistent`), ``feature_field`` (dfd with a field asked for), ``feature_field_distilled`` (one was
        needed and distilled), ``feature_field_s`` (seconds).
    """

    W: np.ndarray
    junction: np.ndarray
    matched: np.ndarray
    method: str
    report: dict = field(default_factory=dict)


def retarget_weights(W, target, num_output_joints, *, confidence=None):
    """W' = B(W): input weights re-indexed onto the output joints.

    Parameters
    ----------
    W : (n, J_in) float array
        Dense input weights.
    target : (J_in,) int array
        Output joint of each input joint (``BoneMap.target``), ``-1`` when unmapped.
    num_output_joints : int
    confidence : (J_in,) float array, optional
        Mapping confidence per input joint.

    Returns
    -------
    Wr : (n, J_R) float64
        Weights of input joints mapped to the same output joint summed; rows renormalized
        (mass on unmapped joints dropped); a row left empty stays all zero.
    c : (n,) float64
        Confidence of each row: ``sum_j W[:, j] confidence[j]`` (1 without ``confidence``).
    """
    W = np.asarray(W, dtype=np.float64)
    target = np.asarray(target, dtype=np.int64)
    ok = target >= 0
    B = sp.csr_matrix((np.ones(int(ok.sum())), (np.flatnonzero(ok), target[ok])),
                      shape=(len(target), num_output_joints))
    Wr = np.asarray((sp.csr_matrix(W) @ B).todense())
    s = Wr.sum(axis=1)
    nz = s > 0
    # leave rows whose sum is already 1 bit-identical (preserved vertices copy them exactly)
    off = nz & (np.abs(s - 1.0) > 1e-12)
    Wr[off] /= s[off, None]
    c = np.ones(len(W)) if confidence is None else W @ np.asarray(confidence, dtype=np.float64)
    return Wr, np.clip(c, 0.0, 1.0)


def closest_point_weights(sources, retargeted, faces, *, tolerance, return_parts=False):
    """The paper's junction weights: closest points of the inputs, blended.

    Parameters
    ----------
    sources : sequence of dict
        Per input, ``FusedSurface.junction_sources[i]``: ``face`` (q,), ``bary`` (q, 3),
        ``distance`` (q,), ``presence`` (q,).
    retargeted : sequence of (n_i, J_R) float arrays
        Retargeted weights of each input, per split vertex.
    faces : sequence of (m_i, 3) int arrays
        Faces of each input.
    tolerance : float
        Inputs farther than the closest one by more than this do not contribute (a far input
        with presence 1, e.g. the other end of a three-character composition, must not).

    Returns
    -------
    W : (q, J_R) float64
        ``sum_i t_i w_i / sum_i t_i`` with ``t_i = p_i / (d_i + eps)`` over the near inputs,
        ``w_i`` the barycentric interpolation of the retargeted weights at the closest point.
    t : (q, I) float64
        The normalized blend factors.
    parts : (I, q, J_R) float64
        Only with ``return_parts``: the ``w_i``, to blend with other factors (:func:`_blend`).
    """
    D = np.stack([np.asarray(s["distance"], np.float64) for s in sources], axis=1)  # (q, I)
    P = np.stack([np.asarray(s["presence"], np.float64) for s in sources], axis=1)
    near = D <= D.min(axis=1, keepdims=True) + tolerance
    eps = 1e-3 * tolerance + 1e-12
    t = np.where(near, np.clip(P, 0.0, 1.0) / (D + eps), 0.0)
    none = t.sum(axis=1) <= 0  # no near input is present there: the closest one decides
    t[none] = np.where(near[none], 1.0 / (D[none] + eps), 0.0)
    t /= t.sum(axis=1, keepdims=True)
    parts = np.stack([
        np.einsum("qk,qkj->qj", np.asarray(s["bary"], np.float64),
                  retargeted[i][np.asarray(faces[i], np.int64)[np.asarray(s["face"], np.int64)]])
        for i, s in enumerate(sources)])
    out, _ = _blend(t, parts)
    return (out, t, parts) if return_parts else (out, t)


def _blend(t, parts):
    """``W = sum_i t_i w_i`` ``(q, J)`` and its spread ``sum_i t_i |w_i - W|_1`` ``(q,)``: how
    much the blended inputs disagree (0 where one input decides or where they agree, as in a
    self-composition). ``t`` (q, I), ``parts`` (I, q, J)."""
    W = np.einsum("qi,iqj->qj", t, parts)
    spread = np.einsum("qi,iq->q", t, np.abs(parts - W[None]).sum(axis=2))
    return W, spread


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


def weld_consistent(V, F, W, junction, max_influences=4):
    """Give every split copy of a position the same weights, so the seams cannot open under
    animation.

    A junction row at a position that a preserved row shares takes that row (the mean of the
    preserved rows there, which normally agree); junction rows sharing a position with no
    preserved row take their mean. Preserved rows never change.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    W : (n, J) float array
        Rows summing to 1.
    junction : (n,) bool array
        Rows whose weights were computed (the others are copied from an input).
    max_influences : int

    Returns
    -------
    W : (n, J) float64
    changed : int
        Junction rows that changed.
    """
    W = np.asarray(W, np.float64).copy()
    junction = np.asarray(junction, bool)
    if not junction.any():
        return W, 0
    _, index, _ = weld(np.asarray(V, np.float64), np.asarray(F, np.int64).reshape(-1, 3))
    k = int(index.max()) + 1 if len(index) else 0
    fixed = ~junction
    n_fixed = np.bincount(index[fixed], minlength=k)
    n_junc = np.bincount(index[junction], minlength=k)
    rows = np.flatnonzero(junction & ((n_fixed[index] > 0) | (n_junc[index] > 1)))
    if not len(rows):
        return W, 0
    groups = np.unique(index[rows])
    pos = np.full(k, -1, np.int64)
    pos[groups] = np.arange(len(groups))
    src = np.flatnonzero(pos[index] >= 0)
    # rows that vote: the preserved ones where a group has any, else its junction rows
    vote = src[np.where(n_fixed[index[src]] > 0, fixed[src], junction[src])]
    S = np.zeros((len(groups), W.shape[1]))
    np.add.at(S, pos[index[vote]], W[vote])
    S /= np.bincount(pos[index[vote]], minlength=len(groups))[:, None]
    new = S[pos[index[rows]]]
    over = np.count_nonzero(new > 0, axis=1) > max_influences
    if over.any():
        new[over] = sparsify(new[over], max_influences)
    changed = np.abs(new - W[rows]).sum(axis=1) > 0
    W[rows] = new
    return W, int(changed.sum())


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
        :func:`rigmix.weights.locality.welded_graph` of ``(V, F)``, when the caller has it.

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
    :func:`rigmix.weights.locality.welded_graph` of ``(V, F)`` when the caller has it."""
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
        Per input, the surface rows it preserves ``(r,)`` int and their weights ``(r, J)``.
    near : float
        Units of ``V``.
    jump : float
    graph : tuple, optional
        :func:`rigmix.weights.locality.welded_graph` of ``(V, F)``, when the caller has it.

    Returns
    -------
    list of (q, J) float64 arrays
        ``parts`` with the jumping far rows replaced; rows non-negative, summing to 1.
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
        X = np.zeros((len(V), P.shape[1]))
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


def smooth_rows(V, F, W, rows, *, iterations=10, alpha=0.5):
    """``w <- (1 - alpha) w + alpha mean(neighbours)`` on ``rows`` (others fixed), on the welded mesh.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    W : (n, J) float array
    rows : (n,) bool array
        Rows to smooth; split vertices of one position move together.
    iterations : int
    alpha : float

    Returns
    -------
    W : (n, J) float64
        Smoothed rows renormalized; other rows unchanged.
    """
    W = np.asarray(W, np.float64).copy()
    rows = np.asarray(rows, bool)
    if not rows.any() or iterations <= 0:
        return W
    Vw, index, G = welded_graph(V, F)
    k = len(Vw)
    A = (G > 0).astype(np.float64)
    deg = np.asarray(A.sum(axis=1)).ravel()
    Ww = np.zeros((k, W.shape[1]))
    cnt = np.bincount(index, minlength=k).astype(np.float64)
    np.add.at(Ww, index, W)
    Ww /= np.maximum(cnt, 1)[:, None]
    free = np.zeros(k, bool)
    free[index[rows]] = True
    free &= deg > 0
    for _ in range(iterations):
        mean = (A @ Ww) / np.maximum(deg, 1)[:, None]
        Ww[free] = (1 - alpha) * Ww[free] + alpha * mean[free]
    out = Ww[index[rows]]
    W[rows] = out / np.maximum(out.sum(axis=1, keepdims=True), 1e-12)
    return W


def to_influences(W, k=4):
    """Dense weights -> ``(joints (n, k) int64, weights (n, k) float64)``, largest first, unused slots 0."""
    W = np.asarray(W, np.float64)
    k = min(k, W.shape[1]) if W.shape[1] else k
    idx = np.argsort(-W, axis=1, kind="stable")[:, :k]
    w = np.take_along_axis(W, idx, axis=1)
    idx = np.where(w > 0, idx, 0)
    return idx.astype(np.int64), w


def blend_weights(surface, inputs, maps, num_output_joints, *, params: WeightParams | None = None,
                  skeleton=None, field=None):
    """W_R on the fused surface.

    Parameters
    ----------
    surface : rigmix.fusion.FusedSurface
    inputs : sequence of rigmix.fusion.FusionInput
        The inputs given to the fusion, in the same order (their ``W`` on the input joints).
    maps : sequence of rigmix.mapping.BoneMap
        B_i per input, same order.
    num_output_joints : int
    method : {"nearest", "inpaint", "dfd"}
    max_influences : int
    match_distance : float
        Matching distance as a fraction of the bounding-box diagonal (``inpaint``, ``dfd``).
    match_angle : float, optional
        Matching normal angle in degrees: 30 for ``inpaint`` (the robust transfer paper), 90
        for ``dfd`` (default). The isosurface normals of a remeshed junction differ from the
        input's by more than 30 degrees on about one junction vertex in ten even where the
        surface is the input's own (self-compositions); the paper's 30 degrees then hands
        correct closest-point weights to the fill. Measured on the self-composition benchmark:
        skinned error over 0.5% of the diagonal in 4 of 37 cases at 60 degrees (up to 2.9%),
        none at 90; the cross-character stretch ratios barely move (Horse+Knight centaur 1.21
        at 60, 1.26 at 90; tail graft 1.04, 1.05).
    blend : {"paper", "harmonic"}, optional
        Blend factors of the inputs' closest-point weights at junction vertices: ``"paper"``
        (``presence / distance``, :func:`closest_point_weights`) or ``"harmonic"``
        (:func:`harmonic_blend_factors`). Default ``"harmonic"`` for ``dfd``, ``"paper"`` for
        the others. Measured (defaults otherwise; Horse+Knight centaur / tail graft stretch
        ratio): paper 2.14 / 1.17, harmonic 1.18 / 0.99; on the mirrored self-compositions
        the harmonic factors lower the junction weight error where the paper's factors jump
        (Velociraptor leg.L 0.034 -> 0.0002, skinned 2.3% -> 0.02% of the diagonal). With
        ``"harmonic"``, an input's closest-point weights that jump from vertex to vertex far
        from it are continued from where they are its own (:func:`continue_far_parts`):
        beast_arms example, junction weight roughness max 0.29 -> 0.17 (inputs' painting
        0.14), stretch 1.03 -> 1.02; Horse+Knight centaur roughness p99 0.45 -> 0.34, stretch
        1.24 -> 1.23.
    match_on_surface : float, optional
        Junction vertices within this fraction of the diagonal of their closest input point are
        matched whatever the normals (:func:`match_junction`'s ``on_surface``). Default 0.005
        for ``dfd`` (the fusion's own fidelity target: such a vertex is on the input's surface),
        0 (off) for ``inpaint``. Measured on the identity self-compositions: RiggedFigure arm.L
        mean error 0.0073 -> 0, skinned 0.46% -> 0; Fox head 0.31% -> 0; the centaur's stretch
        ratio 1.17 -> 1.19 with every vertex within the distance matched.
    min_confidence : float
        Junction vertices whose closest input points are weighted by joints mapped with less
        confidence than this are never matched (filled instead).
    locality : float
        ``dfd``: geodesic radius as a fraction of the diagonal (at least twice the farthest
        unknown vertex's distance to a known one), passed to the fill
        (:func:`rigmix.weights.locality.geodesic_locality`).
    locality_power : float
    smoothing : int
        Iterations of ``w <- 0.5 w + 0.5 mean(neighbours)`` after the fill on the junction
        vertices where the blended inputs disagree (``spread`` of :func:`_blend`
        above ``seam_spread``, grown by ``seam_rings`` rings within the junction; preserved
        vertices fixed). Default 0 for every method. Until the harmonic blend factors, ``dfd``
        used 30 iterations to bring the centaur's stretch ratio from 1.93 to 1.21; it overwrote
        the artist's painting wherever the two inputs differ (mirrored self-compositions: mean
        junction weight error 0.07 -> 0.51 on RiggedFigure's arm), which the harmonic blend
        factors avoid.
    seam_spread : float
    seam_rings : int
    skeleton : rigmix.character.Skeleton, optional
        The output skeleton, its rest pose in the surface's space. ``dfd`` takes its joints'
        names and rest positions for the joint mirror (instead of inferring it from the known
        weights) and its bones as a weak prior where a filled region has no mirror (a band
        across the symmetry plane: a tail's or a neck's root), and lets a reflection that lands
        away from the surface follow its bone onto the mirror bone (a rest pose that differs
        between the sides). Measured with every junction row filled (the self-composition
        benchmark's ``hidden`` protocol), Fox mean junction weight error without / with: tail
        0.71 / 0.37, right leg 0.48 / 0.10; Velociraptor legs, whose rest pose steps forward
        with the left foot, 0.46 / 0.26 and 0.58 / 0.25 with the bones followed.
    feature_field : bool
        ``dfd`` (default True): distill the DFD feature field of the fused surface (settings
        :data:`FIELD_DISTILL`, or ``distill_options``) and trust the mirror prior only where a
        vertex and its mirror point differ in features by no more than the field's known vertices
        differ from theirs (:func:`rigmix.weights.mirror.mirror_prior`); ``field_cache=DIR``
        caches the field.
        Only distilled when some junction vertex is filled and the surface has a mirror plane
        (report ``feature_field_distilled``, ``feature_field_s``).
        False: the prior is trusted by the reflection distance alone (no torch, no distillation).
    **fill_options
        Passed to :func:`rigmix.weights.fill_weights` (``distill_options``, ``field_cache``, or
        ``field=`` a field object, which overrides ``feature_field``). ``dfd`` fills with
        ``iterations`` = :data:`JUNCTION_SMOOTHING` unless given.

    Returns
    -------
    SkinWeights

    Raises
    ------
    InputError
        Unknown method, or inputs and maps that do not match the surface.
    NumericalError
        Non-finite weights (never expected; checked as the stage's contract).
    """
    params = WeightParams() if params is None else params
    method, max_influences, blend = params.method, params.max_influences, params.blend
    match_distance, match_angle, match_on_surface = params.match_distance, params.match_angle, params.match_on_surface
    min_confidence, locality, locality_power = params.min_confidence, params.locality, params.locality_power
    feature_field, smoothing, seam_spread, seam_rings = (params.feature_field, params.smoothing, params.seam_spread,
                                                         params.seam_rings)
    fill_options = params.fill_options()
    if field is not None:
        fill_options["field"] = field
    if method not in WEIGHT_METHODS:
        raise InputError(f"weights: unknown method {method!r}; use one of {', '.join(WEIGHT_METHODS)}")
    if blend is None:
        blend = "harmonic" if method == "dfd" else "paper"
    if blend not in BLEND_FACTORS:
        raise InputError(f"weights: unknown blend {blend!r}; use one of {', '.join(BLEND_FACTORS)}")
    inputs, maps = list(inputs), list(maps)
    lazy = None
    if method == "dfd" and "field" not in fill_options:
        if feature_field:
            lazy = _LazyField(surface.V, surface.F, cache=fill_options.pop("field_cache", None),
                              options={**FIELD_DISTILL, **(fill_options.pop("distill_options", None) or {})})
        fill_options["field"] = lazy if feature_field else False
    if method == "dfd" and skeleton is not None:
        fill_options.setdefault("joint_names", list(skeleton.names))
        fill_options.setdefault("joint_positions", skeleton.rest_worlds()[:, :3, 3])
        fill_options.setdefault("joint_parents", np.asarray(skeleton.parents))
    if len(inputs) != len(maps) or len(inputs) != len(surface.preserved):
        raise InputError(f"weights: {len(inputs)} inputs and {len(maps)} maps for a surface fused from "
                         f"{len(surface.preserved)} inputs")
    N, J = len(surface.V), int(num_output_joints)
    retargeted, conf = [], []
    for x, bm in zip(inputs, maps):
        Wr, c = retarget_weights(x.W, bm.target, J, confidence=bm.confidence)
        retargeted.append(Wr)
        conf.append(c)
    if method == "dfd":  # what the locality may keep where no known vertex witnesses it
        fill_options.setdefault("deforming_joints", np.any([(Wr > 0).any(axis=0) for Wr in retargeted], axis=0))
        fill_options.setdefault("iterations", JUNCTION_SMOOTHING)
    W = np.zeros((N, J))
    junction = np.asarray(surface.junction_vertices, bool)
    pres = np.flatnonzero(~junction)
    for i in range(len(inputs)):
        rows = pres[surface.origin_input[pres] == i]
        W[rows] = retargeted[i][surface.origin_vertex[rows]]
    # rows copied from an input are exact; only rows with more influences than allowed change
    nnz = np.count_nonzero(W > 0, axis=1)
    bad = ~junction & ((nnz > max_influences) | (W.sum(axis=1) <= 0))
    if bad.any():
        W[bad] = sparsify(W[bad], max_influences)
    diag = bounding_box_diagonal(surface.V) if N else 1.0
    jrows = np.flatnonzero(junction)
    matched = np.zeros(N, bool)
    low = np.zeros(N, bool)
    if len(jrows):
        srcs = surface.junction_sources
        _, t, parts = closest_point_weights(srcs, retargeted, [x.F for x in inputs],
                                            tolerance=match_distance * diag, return_parts=True)
        if blend == "harmonic":
            T = np.zeros((N, len(inputs)))
            T[pres, surface.origin_input[pres]] = 1.0
            T[jrows] = t
            graph = welded_graph(surface.V, surface.F)  # built once: at a million faces it is the cost
            t = harmonic_blend_factors(surface.V, surface.F, T, junction, graph=graph)[jrows]
            owned = [pres[surface.origin_input[pres] == i] for i in range(len(inputs))]
            known = [(r, retargeted[i][surface.origin_vertex[r]]) for i, r in enumerate(owned)]
            parts = continue_far_parts(surface.V, surface.F, parts, [s["distance"] for s in srcs], junction, known,
                                       near=ON_SURFACE * diag, graph=graph)
        Wn, spread = _blend(t, parts)
        cj = np.zeros(len(jrows))
        for i, s in enumerate(srcs):
            T = np.asarray(inputs[i].F, np.int64)[np.asarray(s["face"], np.int64)]
            cj += t[:, i] * np.einsum("qk,qk->q", np.asarray(s["bary"]), conf[i][T])
        low[jrows] = cj < min_confidence
        W[jrows] = sparsify(Wn, max_influences)
        if method != "nearest":
            if match_angle is None:
                match_angle = 30.0 if method == "inpaint" else 90.0
            JN = vertex_normals(surface.V, surface.F)[jrows]
            if match_on_surface is None:
                match_on_surface = ON_SURFACE if method == "dfd" else 0.0
            m = match_junction(surface.V[jrows], JN, srcs, [x.V for x in inputs], [x.F for x in inputs],
                               diagonal=diag, match_distance=match_distance, match_angle=match_angle,
                               on_surface=match_on_surface)
            # a vertex copied from an input (a junction both inputs share) lies on the inputs
            # whatever its normal says: box corners differ from every face normal by 45 degrees
            m |= np.asarray(surface.origin_input)[jrows] >= 0
            matched[jrows] = m & ~low[jrows]
            unknown = junction & ~matched
            if unknown.any() and (~unknown).any():
                if method == "dfd" and locality > 0:
                    fill_options.setdefault("locality", locality * diag)
                    fill_options.setdefault("locality_power", locality_power)
                W = fill_weights(surface.V, surface.F, W, unknown, method=method,
                                 max_influences=max_influences, **fill_options)
    seam = np.zeros(N, bool)
    if len(jrows) and smoothing > 0:
        seam[jrows] = spread > seam_spread
        seam = _grow(surface.V, surface.F, seam, seam_rings) & junction
        if seam.any():
            W = smooth_rows(surface.V, surface.F, W, seam, iterations=smoothing)
            W[seam] = sparsify(W[seam], max_influences)
    W, welded_rows = weld_consistent(surface.V, surface.F, W, junction, max_influences)
    if not np.all(np.isfinite(W)):
        raise NumericalError(f"weights: method {method!r} produced non-finite weights on "
                             f"{int((~np.isfinite(W)).any(axis=1).sum())} vertices")
    s = W.sum(axis=1)
    report = {
        "method": method,
        "blend": blend,
        "max_influences": int(np.count_nonzero(W > 0, axis=1).max()) if N else 0,
        "min_sum": float(s.min()) if N else 1.0,
        "max_sum": float(s.max()) if N else 1.0,
        "junction_vertices": int(junction.sum()),
        "matched_vertices": int(matched.sum()),
        "low_confidence_vertices": int(low.sum()),
        "seam_smoothed_vertices": int(seam.sum()),
        "seam_welded_vertices": int(welded_rows),
        "feature_field": bool(method == "dfd" and fill_options.get("field") is not False),
        "feature_field_distilled": bool(lazy is not None and lazy.field is not None),
        "feature_field_s": round(lazy.seconds, 3) if lazy is not None else 0.0,
    }
    log.debug("weights: %s", report)
    return SkinWeights(W=W, junction=junction, matched=matched, method=method, report=report)


class _LazyField:
    """The DFD feature field of the fused surface, distilled on its first evaluation.

    The ``dfd`` fill evaluates it only when some junction vertex is filled and the surface has a
    mirror plane (the field judges the mirror prior); otherwise nothing is distilled. ``field``
    and ``seconds`` tell the report whether it was and what it cost.
    """

    def __init__(self, V, F, *, cache, options):
        self.V, self.F, self.cache, self.options = V, F, cache, options
        self.field = None
        self.seconds = 0.0

    def evaluate(self, X):
        """Unit features ``(q, C)`` at points ``(q, 3)`` of the fused surface's space."""
        if self.field is None:
            t0 = time.perf_counter()
            self.field = distill_feature_field(self.V, self.F, cache=self.cache, **self.options)
            self.seconds = time.perf_counter() - t0
            log.debug("weights: feature field distilled in %.2f s", self.seconds)
        return self.field.evaluate(X)


def _grow(V, F, mask, rings):
    """``mask`` grown by ``rings`` rings of the welded mesh."""
    if rings <= 0 or not mask.any():
        return mask
    Vw, index, G = welded_graph(V, F)
    m = np.zeros(len(Vw), bool)
    m[index[mask]] = True
    A = G > 0
    for _ in range(rings):
        m = m | (A @ m.astype(np.float64) > 0)
    return m[index]
