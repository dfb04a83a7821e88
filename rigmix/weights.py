"""Skinning weights W_R (PIPELINE.md section 4): fill hidden or new weights, sparsify.

:func:`fill_weights` fills the rows of a weight matrix marked unknown from the known rows, on
the mesh welded by position (glTF splits vertices at every seam, so Laplacians and connected
components are only meaningful after welding). Four methods, kept side by side and compared by
``benchmarks/band_fill.py``:

``nearest``
    the weights of the closest point of the known surface (SkinMixer's closest-point transfer).
``harmonic``
    cotangent-Laplacian interpolation with the known vertices fixed.
``inpaint``
    the Robust Skin Weights Transfer anchor (Abdrashitov et al. 2023): squared Laplacian energy
    ``Q = -L + L M^-1 L`` with the known vertices fixed, then 10 iterations of
    ``w <- 0.8 w + 0.2 mean(neighbours)`` on the unknown band.
``dfd``
    the project's method: a prior borrowed from similar known parts (the mirror side found by
    symmetry of the DFD feature field, joints mapped through the skeleton's mirror), blended with
    the inpainting energy as a regularizer. See :func:`_fill_dfd`.

Degenerate geometry
-------------------
Welded flat-shaded assets are closed surfaces, but their cotangent weights can be negative
(obtuse triangles) or infinite (zero-area triangles). The Laplacian used here drops collapsed,
duplicate and zero-area faces, keeps the negative cotangent weights of obtuse triangles (the
P1 stiffness matrix is positive semi-definite for any triangle shape; clamping them made the
benchmark worse), and adds a small uniform graph Laplacian over every welded edge
(``uniform=1e-3`` of the mean absolute cotangent weight), which keeps every connected component
connected for the solver even where faces were dropped. Fills may leave [0, 1] slightly: every
filled row is clamped at zero, sparsified and renormalized. Vertex areas are clamped below at 1% of the mean. Unknown
vertices in a component with no known vertex are not solved for (that block is singular): they
take the weights of the closest known vertex in space, so they are always finite.
"""

from __future__ import annotations

import hashlib
import inspect
import logging
import re
from dataclasses import dataclass

import igl
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from .errors import InputError
from .geometry import bounding_box_diagonal, weld

__all__ = [
    "fill_weights", "sparsify", "feature_field", "mirror_joints", "symmetry_plane", "Plane",
    "FILL_METHODS",
]

log = logging.getLogger(__name__)

FILL_METHODS = ("nearest", "harmonic", "inpaint", "dfd")


def sparsify(W, k=4):
    """Keep the ``k`` largest weights of each row, clamp at zero and renormalize.

    Parameters
    ----------
    W : (n, J) float array
    k : int
        Maximum number of non-zero weights per row (glTF: 4 per JOINTS_n set).

    Returns
    -------
    W : (n, J) float64
        Non-negative, at most ``k`` non-zeros per row, rows summing to 1. A row with no positive
        entry gets weight 1 on its largest entry.
    """
    W = np.nan_to_num(np.asarray(W, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    n, J = W.shape
    out = np.clip(W, 0.0, None)
    if J > k:
        drop = np.argpartition(-out, k - 1, axis=1)[:, k:]  # (n, J-k): all but the k largest
        np.put_along_axis(out, drop, 0.0, axis=1)
    s = out.sum(axis=1)
    empty = s <= 0
    if np.any(empty):
        out[empty] = 0.0
        out[np.flatnonzero(empty), np.argmax(W[empty], axis=1)] = 1.0
        s[empty] = 1.0
    return out / s[:, None]


# --------------------------------------------------------------------------------------------
# Operators on the welded mesh
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Welded:
    """The welded mesh and its operators (cached per ``(V, F)``).

    Attributes
    ----------
    V : (k, 3) welded positions.
    F : (f, 3) clean faces (no collapsed, duplicate or zero-area face).
    index : (n,) welded vertex of each input vertex.
    L : (k, k) regularized cotangent Laplacian (negative semi-definite).
    M : (k,) lumped Voronoi areas (clamped below).
    A : (k, k) 0/1 adjacency over every welded edge.
    component : (k,) connected component label.
    """

    V: np.ndarray
    F: np.ndarray
    index: np.ndarray
    L: sp.csr_matrix
    M: np.ndarray
    A: sp.csr_matrix
    component: np.ndarray


_CACHE: dict[bytes, _Welded] = {}


def _key(*arrays) -> bytes:
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.digest()


def _clean_faces(V, F):
    """Faces without repeated corners, duplicates or (near) zero area, ``(f, 3)``."""
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    if len(F) == 0:
        return F
    _, first = np.unique(np.sort(F, axis=1), axis=0, return_index=True)
    F = F[np.sort(first)]
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    tiny = max(bounding_box_diagonal(V) ** 2 * 1e-14, 1e-300)
    return F[area > tiny]


def _welded(V, F, *, uniform=1e-3) -> _Welded:
    key = _key(V, F, np.float64(uniform))
    if key in _CACHE:
        return _CACHE[key]
    Vw, index, Fw = weld(V, F)
    k = len(Vw)
    # adjacency over every welded edge, including edges of faces that collapse to a segment
    E = np.concatenate([Fw[:, [0, 1]], Fw[:, [1, 2]], Fw[:, [2, 0]]])
    E = E[E[:, 0] != E[:, 1]]
    A = sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(k, k)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64).tocsr()
    _, component = connected_components(A, directed=False)
    Fc = _clean_faces(Vw, Fw)
    if len(Fc):
        C = igl.cotmatrix(Vw, Fc)
        if C.nnz == 0:
            raise RuntimeError("weights: igl.cotmatrix returned an empty matrix")
        C = sp.csr_matrix(C)
        C.resize((k, k))  # igl sizes by the largest referenced vertex
        C.setdiag(0.0)
        C.eliminate_zeros()
        # raw cotangent weights (negative across obtuse angles): the stiffness matrix stays
        # positive semi-definite, and clamping them measurably worsens the fill (Fox 0.39 -> 0.43)
        C.data = np.nan_to_num(C.data, nan=0.0, posinf=0.0, neginf=0.0)
        scale = float(np.abs(C.data).mean()) if C.nnz else 1.0
        m = np.zeros(k)
        mv = np.asarray(igl.massmatrix(Vw, Fc, igl.MASSMATRIX_TYPE_VORONOI).diagonal()).ravel()
        m[: len(mv)] = mv
    else:
        C = sp.csr_matrix((k, k))
        scale = 1.0
        m = np.zeros(k)
    Wgt = C + uniform * scale * A
    L = (Wgt - sp.diags(np.asarray(Wgt.sum(axis=1)).ravel())).tocsr()
    m = np.nan_to_num(m, nan=0.0)
    mean_m = m[m > 0].mean() if np.any(m > 0) else 1.0
    m = np.maximum(m, 1e-2 * mean_m)
    out = _Welded(Vw, Fc, index, L, m, A, component)
    if len(_CACHE) >= 8:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[key] = out
    return out


def _weld_rows(W, index, unknown, k):
    """Welded weights (mean of the known split rows) and the welded unknown mask.

    A welded vertex is unknown as soon as one of its split vertices is.
    """
    unk = np.zeros(k, dtype=bool)
    unk[index[unknown]] = True
    Ww = np.zeros((k, W.shape[1]))
    cnt = np.zeros(k)
    known = ~unknown
    np.add.at(Ww, index[known], W[known])
    np.add.at(cnt, index[known], 1.0)
    ok = cnt > 0
    Ww[ok] /= cnt[ok, None]
    return Ww, unk


# --------------------------------------------------------------------------------------------
# Methods (all on the welded mesh: W (k, J), unk (k,) bool; return (k, J) with known rows kept)
# --------------------------------------------------------------------------------------------


def _nearest_vertex(Vw, W, unk, rows):
    """Weights of the closest known welded vertex for ``rows`` (Euclidean)."""
    tree = cKDTree(Vw[~unk])
    _, i = tree.query(Vw[rows])
    return W[np.flatnonzero(~unk)[i]]


def _fill_nearest(g: _Welded, W, unk, *, mode="vertex"):
    """Closest known welded vertex (``mode="vertex"``, the anchor protocol) or closest point of
    the known surface (faces with three known corners), interpolated (``mode="surface"``)."""
    out = W.copy()
    rows = np.flatnonzero(unk)
    if len(rows) == 0:
        return out
    Fk = g.F[~unk[g.F].any(axis=1)] if len(g.F) else g.F
    if mode == "vertex" or len(Fk) == 0:
        out[rows] = _nearest_vertex(g.V, W, unk, rows)
        return out
    if mode != "surface":
        raise InputError(f"weights: unknown nearest mode {mode!r} (use 'surface' or 'vertex')")
    P = g.V[rows]
    sqd, fi, C = igl.point_mesh_squared_distance(P, g.V, Fk)
    T = Fk[fi]
    B = igl.barycentric_coordinates(C, g.V[T[:, 0]], g.V[T[:, 1]], g.V[T[:, 2]])
    B = np.clip(np.nan_to_num(B, nan=1.0 / 3.0), 0.0, None)
    B /= np.maximum(B.sum(axis=1, keepdims=True), 1e-300)
    fill = np.einsum("nc,ncj->nj", B, W[T])
    # a known vertex outside every known face (isolated, or only on faces touching the band)
    # may be closer than the known surface
    dv, iv = cKDTree(g.V[~unk]).query(P)
    closer = dv**2 < sqd - 1e-15
    fill[closer] = W[np.flatnonzero(~unk)[iv[closer]]]
    out[rows] = fill
    return out


def _solvable(g: _Welded, unk):
    """Unknown vertices whose component has a known vertex (the others would be singular)."""
    has_known = np.zeros(g.component.max() + 1 if len(g.component) else 0, dtype=bool)
    has_known[g.component[~unk]] = True
    return unk & has_known[g.component]


def _solve_fixed(Q, W, unk, solve):
    """Minimize ``w^T Q w`` per column with rows ``~unk`` fixed, for the rows ``solve``."""
    out = W.copy()
    s = np.flatnonzero(solve)
    if len(s) == 0:
        return out
    k = np.flatnonzero(~solve)
    Q = sp.csr_matrix(Q)
    Quu = Q[s][:, s].tocsc()
    rhs = -(Q[s][:, k] @ W[k])
    lu = splu(Quu)
    out[s] = lu.solve(np.ascontiguousarray(rhs))
    return out


def _orphans(g: _Welded, W, unk, solve):
    """Fill the unknown vertices of components without any known vertex: closest known vertex."""
    orphan = unk & ~solve
    if np.any(orphan):
        log.debug("weights: %d unknown vertices in components with no known vertex", orphan.sum())
        W = W.copy()
        W[orphan] = _nearest_vertex(g.V, W, unk, np.flatnonzero(orphan))
    return W


def _fill_harmonic(g: _Welded, W, unk):
    solve = _solvable(g, unk)
    out = _solve_fixed(-g.L, W, unk, solve)
    return _orphans(g, out, unk, solve)


def _bilaplacian(g: _Welded):
    """The squared Laplacian energy of the Robust Skin Weights Transfer, ``-L + L M^-1 L``."""
    return (-g.L + g.L @ sp.diags(1.0 / g.M) @ g.L).tocsr()


def _smooth(g: _Welded, W, unk, *, iterations=10, alpha=0.8):
    """``iterations`` of ``w <- alpha w + (1 - alpha) mean(neighbours)`` on the unknown rows."""
    deg = np.asarray(g.A.sum(axis=1)).ravel()
    rows = np.flatnonzero(unk & (deg > 0))
    if len(rows) == 0:
        return W
    Ar = g.A[rows]
    inv = 1.0 / deg[rows, None]
    W = W.copy()
    for _ in range(iterations):
        W[rows] = alpha * W[rows] + (1.0 - alpha) * (Ar @ W) * inv
    return W


def _fill_inpaint(g: _Welded, W, unk, *, iterations=10, alpha=0.8):
    solve = _solvable(g, unk)
    out = _solve_fixed(_bilaplacian(g), W, unk, solve)
    out = _orphans(g, out, unk, solve)
    return _smooth(g, out, unk, iterations=iterations, alpha=alpha)


# --------------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------------


def fill_weights(V, F, W, unknown, *, method="inpaint", max_influences=4, **options):
    """Fill the unknown rows of a skin weight matrix from the known ones.

    Parameters
    ----------
    V : (n, 3) float array
        Vertex positions (split glTF vertices are fine: the mesh is welded by position inside).
    F : (m, 3) int array
        Triangles over ``V``.
    W : (n, J) float array
        Weights, rows summing to 1; the rows marked unknown are ignored.
    unknown : (n,) bool array
        Rows to fill. A welded vertex is unknown when any of its split vertices is.
    method : {"nearest", "harmonic", "inpaint", "dfd"}
        See the module docstring.
    max_influences : int
        Non-zero weights kept per filled row (the largest), default 4.
    **options
        Method options. ``nearest``: ``mode`` ("vertex", default, or "surface").
        ``inpaint``: ``iterations`` (10), ``alpha`` (0.8). ``dfd``: see :func:`_fill_dfd`.
        All: ``uniform`` (1e-3), the weight of the uniform Laplacian regularizer.

    Returns
    -------
    W_filled : (n, J) float64
        Known rows exactly as given; unknown rows non-negative, with at most
        ``max_influences`` non-zeros, summing to 1, and equal on split vertices of one position.

    Raises
    ------
    InputError
        Shapes disagree, the method is unknown, or no vertex is known at all.
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    W = np.asarray(W, dtype=np.float64)
    unknown = np.asarray(unknown, dtype=bool).reshape(-1)
    n = len(V)
    if W.ndim != 2 or len(W) != n or len(unknown) != n:
        raise InputError(
            f"weights: fill_weights needs V (n,3), W (n,J) and unknown (n,) with the same n; got "
            f"{V.shape}, {W.shape}, {unknown.shape}"
        )
    if method not in FILL_METHODS:
        raise InputError(f"weights: unknown fill method {method!r}; use one of {FILL_METHODS}")
    out = W.copy()
    if not np.any(unknown):
        return out
    if np.all(unknown):
        raise InputError("weights: fill_weights has no known vertex to fill from (all unknown)")
    fill = {"nearest": _fill_nearest, "harmonic": _fill_harmonic, "inpaint": _fill_inpaint,
            "dfd": _fill_dfd}[method]
    uniform = options.pop("uniform", 1e-3)
    allowed = [p.name for p in inspect.signature(fill).parameters.values() if p.kind == p.KEYWORD_ONLY]
    bad = sorted(set(options) - set(allowed))
    if bad:
        raise InputError(f"weights: fill method {method!r} has no option {', '.join(bad)}; "
                         f"its options are {', '.join(allowed) or 'none'}")
    g = _welded(V, F, uniform=uniform)
    Ww, unk = _weld_rows(np.nan_to_num(W), g.index, unknown, len(g.V))
    filled = fill(g, Ww, unk, **options)
    filled = sparsify(filled[unk], max_influences)
    rows = np.zeros(len(g.V), dtype=np.int64)
    rows[np.flatnonzero(unk)] = np.arange(unk.sum())
    out[unknown] = filled[rows[g.index[unknown]]]
    return out



# --------------------------------------------------------------------------------------------
# Symmetry: the plane, the joint mirror, the mirror prior
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Plane:
    """A mirror plane ``{x : x . normal = offset}``.

    Attributes
    ----------
    normal : (3,) unit vector.
    offset : float
    error : float
        Mean distance from the reflected vertices to the closest vertex, over the bounding-box
        diagonal (0 for an exactly symmetric mesh).
    """

    normal: np.ndarray
    offset: float
    error: float = 0.0

    def reflect(self, X):
        """Reflect points ``(n, 3)`` across the plane."""
        X = np.asarray(X, dtype=np.float64)
        return X - 2.0 * ((X @ self.normal) - self.offset)[:, None] * self.normal[None, :]


def symmetry_plane(V, *, tol=0.02, iterations=3):
    """The best mirror plane of a point set among the axis and principal directions.

    Parameters
    ----------
    V : (n, 3) float array
        Vertex positions (welded or not).
    tol : float
        Largest accepted mean reflection error, relative to the bounding-box diagonal.
    iterations : int
        Offset refinements (the plane moves to the mean midpoint of reflected correspondences).

    Returns
    -------
    Plane or None
        ``None`` when no candidate is within ``tol``.
    """
    V = np.unique(np.asarray(V, dtype=np.float64), axis=0)
    diag = bounding_box_diagonal(V)
    if len(V) < 3 or diag <= 0:
        return None
    tree = cKDTree(V)
    c = V.mean(axis=0)
    _, _, axes = np.linalg.svd(V - c, full_matrices=False)
    best = None
    for n in np.vstack([np.eye(3), axes]):
        n = n / np.linalg.norm(n)
        plane = Plane(n, float(0.5 * (V @ n).max() + 0.5 * (V @ n).min()))
        for _ in range(iterations + 1):
            d, i = tree.query(plane.reflect(V))
            plane = Plane(n, float(np.median(0.5 * (V @ n + V[i] @ n))), float(d.mean() / diag))
        if best is None or plane.error < best.error:
            best = plane
    return best if best.error <= tol else None


_SIDES = [
    (r"(?<=[._\-\s])L(?=$|[._\-\s\d])", "R"), (r"(?<=[._\-\s])R(?=$|[._\-\s\d])", "L"),
    (r"Left", "Right"), (r"Right", "Left"), (r"left", "right"), (r"right", "left"),
]


def _swap_side(name: str) -> str | None:
    for pattern, repl in _SIDES:
        swapped, count = re.subn(pattern, repl, name)
        if count:
            return swapped
    return None


def mirror_joints(*, names=None, positions=None, plane=None, tol=0.05):
    """For each joint, its mirror image across the character's symmetry plane.

    Positions win over names when both are given (real rigs misname sides, e.g. the shared
    Knight's ``Thumb.R`` sits on the left hand; CesiumMan's ``arm_joint_L__4_`` pairs with
    ``arm_joint_R``): joint ``j`` maps to the joint closest to its reflection when that joint
    maps back to ``j`` and lies within ``tol`` of the skeleton's extent; names break ties.

    Parameters
    ----------
    names : sequence of str, (J,), optional
    positions : (J, 3) float array, optional
        Joint positions in the mesh's space (bind pose).
    plane : Plane, optional
        Needed with ``positions``.
    tol : float
        Relative to the bounding-box diagonal of ``positions``.

    Returns
    -------
    mirror : (J,) int64
        ``mirror[mirror[j]] == j``; ``mirror[j] == j`` for central or unmatched joints.
    """
    if positions is not None and plane is not None:
        P = np.asarray(positions, dtype=np.float64)
        J = len(P)
        scale = max(bounding_box_diagonal(P), 1e-12)
        R = plane.reflect(P)
        D = np.linalg.norm(R[:, None, :] - P[None, :, :], axis=2)  # (J, J)
        if names is not None:  # names break ties between coincident joints
            same = np.array([[_swap_side(a) == b or (a == b and _swap_side(a) is None)
                              for b in names] for a in names])
            D = D - 1e-6 * scale * same
        m = np.argmin(D, axis=1)
        ok = (D[np.arange(J), m] <= tol * scale) & (m[m] == np.arange(J))
        return np.where(ok, m, np.arange(J)).astype(np.int64)
    if names is not None:
        index = {nm: i for i, nm in enumerate(names)}
        out = np.arange(len(names))
        for i, nm in enumerate(names):
            other = _swap_side(nm)
            if other in index:
                out[i] = index[other]
        out = np.where(out[out] == np.arange(len(names)), out, np.arange(len(names)))
        return out.astype(np.int64)
    raise InputError("weights: mirror_joints needs joint names, or joint positions and a plane")


def _mirror_lookup(g: _Welded, W, unk, plane: Plane, mirror, rows):
    """Weights at the reflection of ``rows`` on the known surface, joints mirrored.

    Only known rows are read (faces with three known corners, interpolated, or the closest
    known vertex): a reflection landing inside the hidden band finds no nearby source.

    Returns
    -------
    P : (r, J) mirrored weights; d : (r,) distance from each reflection to its source.
    """
    known = np.flatnonzero(~unk)
    X = plane.reflect(g.V[rows])
    d, i = cKDTree(g.V[known]).query(X)
    src = W[known[i]]
    Fk = g.F[~unk[g.F].any(axis=1)] if len(g.F) else g.F
    if len(Fk):
        sqd, fi, C = igl.point_mesh_squared_distance(X, g.V, Fk)
        T = Fk[fi]
        B = igl.barycentric_coordinates(C, g.V[T[:, 0]], g.V[T[:, 1]], g.V[T[:, 2]])
        B = np.clip(np.nan_to_num(B, nan=1.0 / 3.0), 0.0, None)
        B /= np.maximum(B.sum(axis=1, keepdims=True), 1e-300)
        ds = np.sqrt(np.maximum(sqd, 0.0))
        closer = ds < d
        src[closer] = np.einsum("nc,ncj->nj", B[closer], W[T[closer]])
        d = np.where(closer, ds, d)
    return src[:, mirror], d


def _edge_scale(g: _Welded):
    """Mean length of the welded edges at each vertex, ``(k,)`` (the diagonal for isolated ones)."""
    A = sp.triu(g.A, k=1).tocoo()
    length = np.linalg.norm(g.V[A.row] - g.V[A.col], axis=1)
    total = np.bincount(A.row, length, len(g.V)) + np.bincount(A.col, length, len(g.V))
    count = np.bincount(A.row, None, len(g.V)) + np.bincount(A.col, None, len(g.V))
    out = np.full(len(g.V), bounding_box_diagonal(g.V))
    out[count > 0] = total[count > 0] / count[count > 0]
    return out


def _mirror_prior(g: _Welded, W, unk, plane: Plane, mirror, *, tol=0.25, field=None,
                  feature_scale=0.5, agreement=0.1, neighbours=16, self_mirror=0.5):
    """The prior of each unknown vertex: its mirror point's known weights, with a confidence.

    The confidence multiplies three terms: the reflection lands on the known surface (distance
    within ``tol`` of the mean edge length at the vertex: a reflection inside the hidden band is
    about an edge away from anything known); the artist painted this region symmetrically (the known
    vertices nearest to it agree with their own mirror points, mean half-L1 within
    ``agreement``: real rigs are not always symmetric, the shared Wasp's legs are not); and,
    with a DFD feature field, the two points look alike (feature distance within
    ``feature_scale``).

    Returns
    -------
    P : (k, J) prior weights (rows of unknown vertices; zero elsewhere).
    c : (k,) confidence in [0, 1] (0: no prior).
    """
    k, J = W.shape
    P = np.zeros_like(W)
    c = np.zeros(k)
    rows = np.flatnonzero(unk)
    known = np.flatnonzero(~unk)
    if len(rows) == 0 or len(known) == 0:
        return P, c
    scale = tol * _edge_scale(g)
    P[rows], d = _mirror_lookup(g, W, unk, plane, mirror, rows)
    conf = np.exp(-((d / scale[rows]) ** 2))
    # symmetry of the artist's painting, measured on the known vertices around each unknown one
    Pk, dk = _mirror_lookup(g, W, unk, plane, mirror, known)
    valid = dk <= scale[known]
    if np.any(valid):
        ek = 0.5 * np.abs(Pk[valid] - W[known[valid]]).sum(axis=1)
        tree = cKDTree(g.V[known[valid]])
        _, nb = tree.query(g.V[rows], k=min(neighbours, int(valid.sum())))
        nb = nb.reshape(len(rows), -1)
        conf *= np.exp(-((ek[nb].mean(axis=1) / agreement) ** 2))
    else:
        conf[:] = 0.0
    # a hidden region that is its own mirror image (a band across the plane) has no visible
    # mirror: the few reflections that land outside it only see the artist's asymmetries
    _, nearest = cKDTree(g.V).query(plane.reflect(g.V[rows]))
    Au = g.A[rows][:, rows]
    _, region = connected_components(Au, directed=False)
    selfish = np.bincount(region, unk[nearest].astype(np.float64)) / np.bincount(region)
    conf[selfish[region] > self_mirror] = 0.0
    if field is not None:
        conf *= np.exp(-((_mirror_feature_distance(g, field, plane)[rows] / feature_scale) ** 2))
    c[rows] = conf
    return P, c


def feature_field(V, F, *, cache=None, seed=0, **distill_options):
    """Distill the DFD feature field of a mesh, on the mesh welded by position.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        Split or welded; the field is distilled on the welded, cleaned surface that
        :func:`fill_weights` uses, so passing it as ``field=`` needs no further work.
    cache : str or Path, optional
        Folder of distilled fields (:func:`dfd.distill.distill`'s ``cache``).
    seed : int
    **distill_options
        Passed to :func:`dfd.distill.distill` (``encoder``, ``n_views``, ``resolution``...).

    Returns
    -------
    dfd.field.FeatureField
        ``field.evaluate(points (q, 3)) -> (q, C)`` unit features.
    """
    from dfd.distill import distill  # heavy (torch): imported where used

    g = _welded(np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64).reshape(-1, 3))
    return distill(g.V, g.F, seed=seed, cache=None if cache is None else str(cache), **distill_options)


_FEATURES: dict[tuple, tuple] = {}
_PLANES: dict[bytes, Plane | None] = {}


def _mirror_feature_distance(g: _Welded, field, plane: Plane):
    """``(k,)`` feature distance between each welded vertex and its reflection.

    Evaluated once per (field, mesh, plane) and cached: a field evaluation costs far more than
    a band fill, and the benchmark fills dozens of bands of one character.
    """
    key = (id(field), _key(g.V, plane.normal, np.float64(plane.offset)))
    if key not in _FEATURES:
        if len(_FEATURES) >= 8:
            _FEATURES.pop(next(iter(_FEATURES)))
        f0 = _evaluate(field, g.V)
        f1 = _evaluate(field, plane.reflect(g.V))
        _FEATURES[key] = (field, np.linalg.norm(f0 - f1, axis=1))  # holding field pins its id
    return _FEATURES[key][1]


def _evaluate(field, X):
    """Unit features ``(n, C)`` of a feature field (an object with ``evaluate`` or a callable)."""
    f = field.evaluate(X) if hasattr(field, "evaluate") else field(X)
    f = np.asarray(f, dtype=np.float64)
    return f / np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12)


def _solve_prior(g: _Welded, W, unk, P, c, *, strength=10.0):
    """Minimize ``w^T Q w + lam sum_v c_v m_v |w_v - P_v|^2`` over the unknown rows.

    ``Q`` is the inpainting energy; ``lam`` is ``strength`` times the mean diagonal of ``Q``
    over the unknown rows per unit area, so that ``strength`` is scale free.
    """
    Q = _bilaplacian(g)
    s = np.flatnonzero(unk)
    if len(s) == 0:
        return W.copy()
    reg = c[s] * g.M[s]
    # rows with a prior are solvable even in a component without any known vertex
    solve = _solvable(g, unk) | (unk & (c > 1e-6))
    comp_ok = np.zeros(g.component.max() + 1, dtype=bool)
    comp_ok[g.component[solve]] = True
    solve = unk & comp_ok[g.component]
    s = np.flatnonzero(solve)
    out = W.copy()
    if len(s):
        Qss = Q[s][:, s]
        lam = strength * float(Qss.diagonal().mean() / g.M[s].mean())
        reg = lam * c[s] * g.M[s]
        kn = np.flatnonzero(~solve)
        A = (Qss + sp.diags(reg)).tocsc()
        rhs = -(Q[s][:, kn] @ W[kn]) + reg[:, None] * P[s]
        out[s] = splu(A).solve(np.ascontiguousarray(rhs))
    return _orphans(g, out, unk, solve)


def _fill_dfd(g: _Welded, W, unk, *, field=None, plane=None, joint_mirror=None,
              joint_names=None, joint_positions=None, mirror_tol=0.25, strength=10.0,
              iterations=0, alpha=0.8, field_cache=None, distill_options=None):
    """The project's fill: the inpainting energy pulled toward a prior from similar known parts.

    Prior: each unknown vertex reflected across the symmetry plane (given, or detected on the
    welded mesh) lands on the known surface of the other side; its weights, with joints mapped
    through the skeleton's mirror, are the prior, trusted by the reflection distance and, with a
    DFD feature field, by the feature agreement of the two points. Where no prior exists (a
    central joint, or the mirror point is hidden too), the fill is the inpainting.
    """
    J = W.shape[1]
    if field is False:  # ablation: geometry only
        field = None
    elif field is None:
        from dfd.distill import distill  # heavy (torch): imported where used

        field = distill(g.V, g.F, cache=None if field_cache is None else str(field_cache),
                        **(distill_options or {}))
    if plane is None:
        key = _key(g.V)
        if key not in _PLANES:
            _PLANES[key] = symmetry_plane(g.V)
        plane = _PLANES[key]
    if plane is None:
        return _fill_inpaint(g, W, unk, iterations=iterations, alpha=alpha)
    if joint_mirror is None:
        if joint_positions is not None or joint_names is not None:
            joint_mirror = mirror_joints(names=joint_names, positions=joint_positions, plane=plane)
        else:
            joint_mirror = _mirror_from_weights(g, W, unk, plane)
    mirror = np.asarray(joint_mirror, dtype=np.int64).reshape(J)
    P, c = _mirror_prior(g, W, unk, plane, mirror, tol=mirror_tol, field=field)
    out = _solve_prior(g, W, unk, P, c, strength=strength)
    return _smooth(g, out, unk, iterations=iterations, alpha=alpha) if iterations else out


def _mirror_from_weights(g: _Welded, W, unk, plane):
    """Joint mirror from the weighted centroids of the known vertices (no skeleton given)."""
    known = ~unk
    mass = W[known].sum(axis=0)
    cen = (W[known].T @ g.V[known]) / np.maximum(mass, 1e-12)[:, None]
    m = mirror_joints(positions=cen, plane=plane)
    m[mass <= 1e-9] = np.flatnonzero(mass <= 1e-9)
    return np.where(m[m] == np.arange(len(m)), m, np.arange(len(m)))
