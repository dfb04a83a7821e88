"""One junction: blended field, isosurface, cut, bridges, remesh (PIPELINE.md section 3).

Helper of :func:`rigmix.fusion.fuse_surfaces`. :func:`junction_for_cluster` runs the steps in
order: blend the inputs' fields (:func:`_field_for_cluster`), take the isosurface, cut it where
preserved faces take over (:func:`_cut_isosurface`), bridge its loops to the seams, cutting it
back where a bridge crosses it (:func:`_bridge_without_crossings`), and remesh the result with
the seams fixed, keeping the shape where that costs no slivers (:func:`_remesh_bridged`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from functools import partial

import numpy as np

from ..geometry import closest_points
from .fields import blend_attach, blend_cap, blend_replace, signed_distance_at
from .junction import (
    Loop,
    boundary_loops,
    bridge_loops,
    clip_mesh,
    isosurface,
    keep_components_touching,
    loop_distance,
    match_loops,
    orientation_agrees,
    remove_unreferenced,
)
from .meshutil import cross3, dihedral_angles, intersecting_face_pairs, triangle_min_angles
from .remesh import (
    collapse_to_improve_angles,
    flip_doubled_edges,
    flip_to_improve_angles,
    insert_points,
    is_edge_manifold,
    refine_where_stray,
    relocate_poor_vertices,
    remesh_junction,
    smooth_interior,
    snap_to_points,
    untangle,
)
from .seams import pinched_faces

log = logging.getLogger(__name__)

__all__ = ["ClusterJunction", "bridge_seams", "junction_for_cluster", "project_to_inputs", "remesh_keeping_features"]


def _field_for_cluster(n, inputs_fields, actions, band):
    """Blend the per-input fields at ``n`` samples (a grid's voxels): dominant action per sample."""
    involved = [k for k, a in enumerate(actions) if a.a in inputs_fields and a.b in inputs_fields]
    if not involved:
        vals = [blend_cap(d, p, band=band) for d, p in inputs_fields.values()]
        return np.min(np.stack(vals), axis=0)
    best = np.full(n, np.inf)
    out = np.full(n, band)
    for k in involved:
        a = actions[k]
        d0, p0 = inputs_fields[a.a]
        d1, p1 = inputs_fields[a.b]
        f = blend_replace(d0, p0, d1, p1, band=band) if a.kind == "replace" else blend_attach(d0, p0, d1, p1, band=band)
        s = np.where(p0 + p1 > 0, p1 / np.maximum(p0 + p1, 1e-12), 0.5)
        score = 0.1 * np.abs(f) / band + 0.9 * 2.0 * np.abs(0.5 - s)
        take = score < best
        out[take] = f[take]
        best[take] = score[take]
    return out


#: :func:`project_to_inputs` with ``agreeing``: the present inputs agree where the length of
#: their closest faces' mean unit normal is at least this (cos 15 degrees: two normals within 30)
AGREEING_NORMALS = float(np.cos(np.radians(15.0)))


def project_to_inputs(U, nfixed, pres, surfaces, inputs_fields, h, max_voxels, clear=None, *, agreeing=False):
    """Pull free junction vertices onto the presence-weighted average of their closest points.

    The isosurface is only accurate to a fraction of a voxel at creases; where the inputs agree
    (a character composed with itself) this puts the junction back on the input surface. Moves
    are limited to ``max_voxels`` voxels so that a wide blend between different shapes keeps
    the field's shape. With ``clear`` (points ``(k, 3)`` -> ``(k,) bool``), a vertex whose
    target is not clear stays (the input surface runs under a kept part there).

    With ``agreeing`` (a plain junction, whose shape is the field's), a vertex moves only where
    the inputs agree and its target is within ``max_voxels`` voxels: not where two present
    inputs' closest points lie more than a voxel apart (pulling towards surfaces that run under
    or beside it would put back the crease of their union that the smoothing took away), nor
    where the target is farther (a move clamped to that length bends the blend between
    different shapes along the line where the clamp starts).
    """
    import igl

    if max_voxels <= 0 or len(U) <= nfixed:
        return U
    Q = U[nfixed:]
    acc = np.zeros_like(Q)
    wsum = np.zeros(len(Q))
    if agreeing:
        lo = np.full(Q.shape, np.inf)  # bounding box of the present inputs' closest points
        hi = np.full(Q.shape, -np.inf)
        nsum = np.zeros_like(Q)  # their faces' unit normals, summed, and how many
        ncount = np.zeros(len(Q))
    for i in inputs_fields:
        P = pres[i]
        Fs = surfaces[i]
        if len(Fs) == 0:
            continue
        d2, fid, C = closest_points(Q, P.welded.V, Fs, (max_voxels + 2.0) * h)
        T = Fs[fid]
        B = igl.barycentric_coordinates(C, P.welded.V[T[:, 0]], P.welded.V[T[:, 1]], P.welded.V[T[:, 2]])
        B = np.clip(np.nan_to_num(B, nan=1 / 3), 0, 1)
        p = np.einsum("nk,nk->n", B / np.maximum(B.sum(axis=1, keepdims=True), 1e-12), P.p_welded[T])
        w = p / (np.sqrt(d2) + h)
        acc += w[:, None] * C
        wsum += w
        if agreeing:
            present = p > 0
            lo[present] = np.minimum(lo[present], C[present])
            hi[present] = np.maximum(hi[present], C[present])
            Vw = P.welded.V
            nf = cross3(Vw[T[:, 1]] - Vw[T[:, 0]], Vw[T[:, 2]] - Vw[T[:, 0]])
            nf /= np.maximum(np.linalg.norm(nf, axis=1, keepdims=True), 1e-300)
            nsum[present] += nf[present]
            ncount += present
    ok = wsum > 0
    if agreeing:
        spread = np.linalg.norm(np.where(np.isfinite(hi - lo), hi - lo, 0.0), axis=1)
        # two surfaces that meet (the crease of their union) have close closest points but
        # normals apart: agreement asks for both (mean normal within about 15 degrees of each),
        # unless the points are one (a crease of one surface, composed with itself)
        aligned = np.linalg.norm(nsum, axis=1) >= AGREEING_NORMALS * np.maximum(ncount, 1)
        same_point = spread <= 0.05 * h
        ok &= (spread <= h) & (aligned | same_point)
    target = np.where(ok[:, None], acc / np.maximum(wsum, 1e-300)[:, None], Q)
    move = target - Q
    n = np.linalg.norm(move, axis=1)
    if agreeing:
        move[n > max_voxels * h] = 0.0
    else:
        move *= np.minimum(1.0, max_voxels * h / np.maximum(n, 1e-300))[:, None]
    if clear is not None:
        move[~clear(Q + move)] = 0.0
    out = U.copy()
    out[nfixed:] = Q + move
    return out


def _position_keys(P):
    """One comparable key per row of ``P`` (exact positions)."""
    P = np.ascontiguousarray(np.asarray(P, np.float64).reshape(-1, 3))
    return P.view(np.dtype((np.void, P.dtype.itemsize * 3))).ravel()


def _preserved_edges_between(pres, preserved, keys, fid_to_final):
    """Edges of preserved faces whose two ends are junction border vertices, in final indices.

    The junction must not contain them too (three faces on one edge).
    """
    nf = max(keys.values(), default=-1) + 1
    final = np.full(nf, -1, np.int64)
    for k, v in fid_to_final.items():
        final[k] = v
    out = []
    for i, P in enumerate(pres):
        T = P.welded.F[preserved[i]]
        mine = [(w, k) for (src, w), k in keys.items() if src == i]
        if len(T) == 0 or not mine:
            continue
        look = np.full(len(P.welded.V), -1, np.int64)
        ws, ks = np.array(mine, np.int64).T
        look[ws] = final[ks]
        E = np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]])
        L = look[E]
        out.append(L[(L >= 0).all(axis=1)])
    return np.concatenate(out) if out else np.zeros((0, 2), np.int64)


def _replaced_input_vertices(pres, inputs, junction_masks, preserved, grid):
    """Welded vertices of the inputs' replaced faces inside ``grid``: present (``p > 0``), not
    on a preserved face, and at no position a preserved face of any input has (moving a
    junction vertex there would weld it into a seam). Returns ``(k, 3)`` positions."""
    pts = []
    for i in inputs:
        P = pres[i]
        T = P.welded.F[junction_masks[i]]
        if len(T) == 0:
            continue
        v = np.unique(T.ravel())
        on_kept = np.zeros(len(P.welded.V), bool)  # seam vertices are in the output already
        on_kept[P.welded.F[preserved[i]].ravel()] = True
        v = v[(P.p_welded[v] > 0) & ~on_kept[v]]
        X = P.welded.V[v]
        pts.append(X[np.all((X >= grid.origin) & (X <= grid.upper), axis=1)])
    X = np.unique(np.concatenate(pts), axis=0) if pts else np.zeros((0, 3))
    if len(X) == 0:
        return X
    kept = [P.welded.V[np.unique(P.welded.F[preserved[i]].ravel())] for i, P in enumerate(pres)]
    K = np.concatenate(kept) if kept else np.zeros((0, 3))
    return X[~np.isin(_position_keys(X), _position_keys(K))]


def _replaced_dihedral(pres, inputs, junction_masks, grid, percentile=95.0):
    """How much the inputs' surface the junction replaces creases: the ``percentile`` of the
    dihedral angles between neighbouring replaced welded faces inside ``grid`` (degrees, pooled
    over ``inputs``; None without such a pair)."""
    samples = []
    for i in inputs:
        P = pres[i]
        T = P.welded.F[junction_masks[i]]
        inside = np.all((P.welded.V >= grid.origin) & (P.welded.V <= grid.upper), axis=1)
        T = T[inside[T].all(axis=1)]
        if len(T):
            samples.append(dihedral_angles(P.welded.V, T))
    pooled = np.concatenate(samples) if samples else np.zeros(0)
    return float(np.percentile(pooled, percentile)) if len(pooled) else None


def _dihedral_p95(V, F):
    """95th percentile of the dihedral angles of ``(V, F)`` (degrees; 0 without a face pair)."""
    a = dihedral_angles(V, F)
    return float(np.percentile(a, 95)) if len(a) else 0.0


def _surface_input_vertices(X, grid, field3, h):
    """The points of ``X`` where the sampled blended field is within a quarter voxel of 0."""
    from scipy.ndimage import map_coordinates

    if len(X) == 0:
        return X
    ijk = (X - grid.origin) / grid.voxel
    f = map_coordinates(field3, ijk.T, order=1, mode="nearest")
    return X[np.abs(f) < 0.25 * h]


def _clear_of_parts(X, grid, floor3):
    """``(k,) bool``: the points ``X`` (k, 3) outside the kept closed parts' clearance, where
    the sampled field floor ``floor3`` (:func:`junction_for_cluster`'s ``floor`` on the grid's
    shape) is not positive."""
    from scipy.ndimage import map_coordinates

    if len(X) == 0:
        return np.ones(0, bool)
    ijk = (np.asarray(X, np.float64) - grid.origin) / grid.voxel
    return map_coordinates(floor3, ijk.T, order=1, mode="nearest") <= 0.0


def _separate_coincident(U, G, nfixed):
    """Nudge free vertices that sit exactly on another vertex (a projection onto an input
    corner): welded by position, they would pinch the surface into non-manifold edges."""
    from ..geometry import weld
    from .meshutil import vertex_adjacency

    _, idx = weld(U)
    cnt = np.bincount(idx, minlength=idx.max() + 1 if len(idx) else 0)
    dup = np.flatnonzero(cnt[idx] > 1)
    # keep one copy in place: a fixed vertex if the group has one, else the first
    first = {}
    for v in sorted(dup, key=lambda v: (v >= nfixed, v)):
        first.setdefault(idx[v], v)
    move = [v for v in dup if v >= nfixed and first[idx[v]] != v]
    if not move:
        return U
    A = vertex_adjacency(G, len(U)).astype(np.float64)
    deg = np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1)
    C = (A @ U) / deg[:, None]
    U = U.copy()
    move = np.asarray(move)
    U[move] += 0.05 * (C[move] - U[move])
    return U


def _field_at_points(X, pres, surfaces, inputs_fields, actions, band):
    """The blended field of :func:`_field_for_cluster` at points ``X`` (k, 3), from exact
    distances (:func:`.fields.signed_distance_at`)."""
    fields = {}
    for i in inputs_fields:
        d, p = signed_distance_at(X, pres[i].welded.V, surfaces[i], pres[i].p_welded, band=band)
        fields[i] = (d, p[:, 0])
    return _field_for_cluster(len(X), fields, actions, band)


def _input_vertices_on_surface(X, pres, surfaces, inputs_fields, actions, band, tol):
    """The points of ``X`` on the blended surface by the exact field (``|f| <= tol``).

    Marching cubes rounds the corners and loses the thin parts of low-poly inputs (measured:
    up to 1.8% of the bounding-box diagonal on self-compositions); where the exact blended
    field says an input vertex lies on the surface, the junction can keep it.
    """
    if len(X) == 0:
        return X
    f = _field_at_points(X, pres, surfaces, inputs_fields, actions, band)
    return X[np.abs(f) <= tol]


def _spread(X, priority, spacing, avoid=None, avoid_spacing=None):
    """Greedy subset of ``X`` (highest ``priority`` first) at least ``spacing`` apart and
    ``avoid_spacing`` (default ``spacing``) from the points ``avoid``. Returns indices into ``X``."""
    from scipy.spatial import cKDTree

    X = np.asarray(X, np.float64).reshape(-1, 3)
    order = np.argsort(-np.asarray(priority))
    free = np.ones(len(X), bool)
    if avoid is not None and len(avoid) and len(X):
        free = cKDTree(avoid).query(X)[0] >= (spacing if avoid_spacing is None else avoid_spacing)
    # picked points by cell of side ``spacing``: a point closer than that is in a neighbouring cell
    cells: dict = {}
    key = np.floor(X / spacing).astype(np.int64) if spacing > 0 else np.zeros((len(X), 3), np.int64)
    near = [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)]
    pick: list[int] = []
    for k in order:
        if not free[k]:
            continue
        cx, cy, cz = key[k]
        close = [q for d in near for q in cells.get((cx + d[0], cy + d[1], cz + d[2]), ())]
        if close and np.min(np.linalg.norm(X[close] - X[k], axis=1)) < spacing:
            continue
        pick.append(int(k))
        cells.setdefault((cx, cy, cz), []).append(int(k))
    return np.asarray(pick, np.int64)


def _angle_p05(V, F):
    """5th percentile of the triangles' minimum angles, degrees (0 without triangles)."""
    return float(np.percentile(triangle_min_angles(V, F), 5)) if len(F) else 0.0


def remesh_keeping_features(V, F, fixed, target, iterations, tol, rounds, points=None, points_tol=None,
                            max_insert=None, refine_rounds=0, min_edge=None, forbidden=None):
    """Remesh with ``fixed`` kept, then refine and pin where the result strays.

    Remeshing to the neighbouring edge length chords off the corners and thin parts of the
    surface it follows. The remeshed surface is refined first: for at most ``refine_rounds``
    rounds, its faces farther than ``tol`` from the reference are split, the new vertices on the
    reference (:func:`.remesh.refine_where_stray`, edges down to ``2 min_edge``), then its edges
    flipped and the free vertices of poor triangles moved along the reference where that raises
    the angles (:func:`.remesh.flip_to_improve_angles`, never making a ``forbidden`` edge;
    :func:`.remesh.relocate_poor_vertices`), so that the triangles follow the curvature the
    target edge missed with the creases of a finer mesh, not of a spike. Then for at most ``rounds`` rounds, the
    vertices of the reference ``(V, F)`` still farther than ``tol`` from the result, farthest
    first, at least half a target edge apart and a quarter from the kept vertices, are inserted
    into it (:func:`.remesh.insert_points`: a nearby free vertex moves onto one, or a face or
    edge is split) and kept. Before the remeshing, the ``points`` (exact surface points: input
    corners) the reference itself misses by more than ``points_tol`` (default ``tol``) and that
    lie within ``max_insert`` of it are inserted into the reference.

    Parameters
    ----------
    V : (n, 3) float array, F : (m, 3) int array
        The reference surface: edge-manifold, its border vertices among ``fixed``.
    fixed : (k,) int array
        Vertices of ``V`` kept exactly (the seams).
    target : float
        Target edge length (same units as ``V``).
    iterations : int
        Remeshing iterations.
    tol : float
        Same units as ``V``; 0 gives one plain remeshing.
    rounds : int
        Rounds of kept vertices at most.
    points : (p, 3) float array, optional
        Exact surface points to keep where the reference misses them.
    points_tol, max_insert : float, optional
        See above; ``max_insert`` defaults to ``4 tol``.
    refine_rounds : int
        Rounds of refinement at most.
    min_edge : float, optional
        Edges shorter than twice this are not split (default a fifth of ``target``).
    forbidden : (e, 2) int array, optional
        Edges between seam vertices, numbered as in the output (the order of ``fixed``), that
        no flip may make.

    Returns
    -------
    U : (p, 3) float64, G : (q, 3) int64
        ``U[:len(fixed)] == V[fixed]``, then the kept feature vertices.
    nfix : int
        Number of kept vertices (``fixed`` and features).
    reference : (RV, RF)
        The reference with the inserted points.
    """
    import igl

    fixed = np.asarray(fixed, np.int64)
    points = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64).reshape(-1, 3)
    reach = 4.0 * tol if max_insert is None else max_insert
    if tol > 0 and len(points):
        dX = np.sqrt(igl.point_mesh_squared_distance(points, V, F)[0])
        lost = dX > (tol if points_tol is None else points_tol)
        X = points[lost][_spread(points[lost], dX[lost], 0.5 * target, avoid=V[fixed], avoid_spacing=0.15 * target)]
        if len(X):
            V, F, _ = insert_points(V, F, np.isin(np.arange(len(V)), fixed), X, max_dist=reach)
    U, G = remesh_junction(V, F, fixed, target=target, iterations=iterations)
    keep = np.arange(len(fixed))  # remesh_junction puts the fixed vertices first
    if tol <= 0:
        return U, G, len(keep), (V, F)
    for _ in range(refine_rounds):
        if len(G) >= 0.5 * len(F):  # finer than the reference, at voxel size, is no closer to it
            break
        U, G, split = refine_where_stray(U, G, (V, F), tol=tol, min_edge=0.2 * target if min_edge is None else min_edge)
        if not split:
            break
        G = flip_to_improve_angles(U, G, forbidden=forbidden)
        U = relocate_poor_vertices(U, G, len(fixed), surface=(V, F))
        G = flip_to_improve_angles(U, G, forbidden=forbidden)
    for _ in range(rounds):
        d = np.sqrt(igl.point_mesh_squared_distance(V, U, G)[0])
        far = np.flatnonzero(d > tol)
        far = far[~np.isin(far, fixed)]
        pick = far[_spread(V[far], d[far], 0.5 * target, avoid=U[keep], avoid_spacing=0.25 * target)]
        if not len(pick):
            break
        U, G, placed = insert_points(U, G, np.isin(np.arange(len(U)), keep), V[pick], max_dist=np.inf)
        placed = placed[~np.isin(placed, keep)]
        if not len(placed):
            break
        keep = np.concatenate([keep, placed])
    order = np.concatenate([keep, np.setdiff1d(np.arange(len(U)), keep)])
    new = np.empty(len(U), np.int64)
    new[order] = np.arange(len(U))
    U, G = U[order], new[G]
    U[:len(fixed)] = V[fixed]
    return U, G, len(keep), (V, F)


def _cut_isosurface(Vi, Fi, pres, preserved, depth):
    """Remove the isosurface where a preserved face is closer than ``depth``.

    Parameters
    ----------
    Vi : (k, 3) float array, Fi : (q, 3) int array
        The isosurface.
    pres : list of Presence
    preserved : list of (m_i,) bool arrays
        Per input, preserved (or copied) welded faces; secondary components do not cut.
    depth : float
        Same units as the meshes.

    Returns
    -------
    Vc : (k', 3) float array, Fc : (q', 3) int array
        What is left, with no boundary passing twice through one vertex (such faces are opened
        up, three rounds at most).
    """
    import igl

    if len(Vi) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    dmin = np.full(len(Vi), np.inf)
    for i, P in enumerate(pres):
        Fp = P.welded.F[preserved[i] & ~P.secondary]
        if len(Fp) == 0:
            continue
        d2, _, _ = igl.point_mesh_squared_distance(Vi, P.welded.V, Fp)
        dmin = np.minimum(dmin, np.sqrt(d2))
    Vc, Fc, _ = clip_mesh(Vi, Fi, dmin - depth)
    for _ in range(3):  # boundaries through one vertex twice: open them up
        bad = pinched_faces(Fc) if len(Fc) else np.zeros(0, bool)
        if not bad.any():
            break
        Vc, Fc, _ = remove_unreferenced(Vc, Fc[~bad])
    return Vc, Fc


@dataclass(frozen=True)
class _Bridged:
    """The junction before remeshing: the cut isosurface with its loops bridged to the seams.

    Attributes
    ----------
    V : (k, 3) float64
        The ``n_iso`` vertices of the kept isosurface (and the centres of the fans closing its
        unclaimed holes), then the seam loop vertices.
    F : (q, 3) int64
        Isosurface and fan faces, then the ``n_bridge`` bridge faces.
    n_iso : int
    keys : dict
        ``(input, welded vertex)`` of each seam vertex -> its index among the seam vertices
        (``V[n_iso + index]``).
    n_bridge : int
    seam_edge : float
        Mean edge length of the seam loops (the voxel without loops).
    fans : dict
        Fan centre vertex -> ``(l, 3)`` positions of the hole loop it closes.
    unmatched_preserved_loops, unmatched_iso_loops, orientation_warnings : int
        Seam loops left without a partner, isosurface holes closed by a fan, and partners of
        opposite orientation bridged anyway.
    capped_loops : int
        Seam loops without a partner closed by a fan (no wider than the matching reach).
    """

    V: np.ndarray
    F: np.ndarray
    n_iso: int
    keys: dict
    n_bridge: int
    seam_edge: float
    fans: dict
    unmatched_preserved_loops: int
    unmatched_iso_loops: int
    orientation_warnings: int
    capped_loops: int = 0

    @property
    def without_partner(self) -> int:
        """Seam loops bridged to nothing, capped or not."""
        return self.unmatched_preserved_loops + self.capped_loops


def _diameter(X):
    """Largest distance between two of the points ``X`` ``(k, 3)``."""
    return float(np.sqrt(((X[:, None, :] - X[None, :, :]) ** 2).sum(axis=-1).max())) if len(X) else 0.0


def bridge_seams(Vc, Fc, loops, h, cut_voxels):
    """Match the seam loops to the loops of the cut isosurface (or to each other across inputs)
    and bridge them.

    Parameters
    ----------
    Vc : (k, 3) float array, Fc : (q, 3) int array
        The cut isosurface (:func:`_cut_isosurface`).
    loops : list of Loop
        Seam loops of the cluster.
    h : float
        Voxel (same units as the meshes).
    cut_voxels : float
        The cut depth in voxels; loops farther apart than the cut leaves room for stay unmatched.

    Returns
    -------
    _Bridged
        Isosurface components that meet no matched loop are dropped; holes no seam claims are
        closed by a fan.
    """
    unmatched_iso = warnings = 0
    fans = {}  # fan centre vertex -> the positions of the hole's loop
    iso_loops, _ = boundary_loops(Vc, Fc, -1) if len(Fc) else ([], [])
    # match preserved loops to isosurface loops (or to each other across inputs)
    edge = np.mean([np.linalg.norm(np.diff(np.vstack([L.positions, L.positions[:1]]), axis=0), axis=1).mean()
                    for L in loops]) if loops else h
    max_cost = max(cut_voxels * h * 3.0 + 2.0 * h, 1.5 * edge)
    pairs = match_loops(loops, iso_loops, max_cost=max_cost)
    matched_iso = [j for i, kind, j in pairs if kind == "iso"]
    matched_pres = {i for i, _, _ in pairs} | {j for _, kind, j in pairs if kind == "preserved"}
    # keep the isosurface components that meet a matched loop
    if len(Fc) and matched_iso:
        keepf = keep_components_touching(Fc, len(Vc), np.concatenate([iso_loops[j].vertices for j in matched_iso]))
        Vc2, Fc2, old = remove_unreferenced(Vc, Fc[keepf])
        new = np.full(len(Vc), -1, np.int64)
        new[old] = np.arange(len(old))
        iso_loops = [Loop(-1, new[L.vertices], L.positions) for L in iso_loops]
        Vc, Fc = Vc2, Fc2
        # isosurface holes no seam claims (cut around a preserved speck): closed by a fan
        matched_sets = [frozenset(iso_loops[j].vertices.tolist()) for j in matched_iso]
        remaining, _ = boundary_loops(Vc, Fc, -1)
        extra_v, extra_f = [], []
        for L in remaining:
            if frozenset(L.vertices.tolist()) in matched_sets:
                continue
            c = len(Vc) + len(extra_v)
            extra_v.append(L.positions.mean(axis=0))
            extra_f += [(L.vertices[k], L.vertices[k - 1], c) for k in range(len(L.vertices))]
            fans[c] = L.positions
            unmatched_iso += 1
        if extra_v:
            Vc = np.concatenate([Vc, np.asarray(extra_v)])
            Fc = np.concatenate([Fc, np.asarray(extra_f, np.int64)])
    else:
        Vc, Fc = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    # a seam loop no partner reaches is a hole the isosurface cannot fill when it is no wider
    # than that reach (a face or two of a part let go at a conflict) or lies within two voxels of a
    # bridged loop of its input (a lining the isosurface cannot resolve): closed by a fan, so that the
    # surface stays closed and the rest of the junction is bridged
    def beside_bridged(i):
        return any(loops[j].source == loops[i].source
                   and loop_distance(loops[i].positions, loops[j].positions) <= 2.0 * h for j in matched_pres)

    capped = [i for i in range(len(loops))
              if i not in matched_pres and (_diameter(loops[i].positions) <= max_cost or beside_bridged(i))]
    if capped:
        Vc = np.concatenate([Vc, np.asarray([loops[i].positions.mean(axis=0) for i in capped])])
    # junction vertex table: isosurface vertices, then preserved loop vertices (fixed)
    keys: dict[tuple[int, int], int] = {}
    fixed_pos = []

    def fixed_id(src, v, pos):
        k = (int(src), int(v))
        if k not in keys:
            keys[k] = len(fixed_pos)
            fixed_pos.append(pos)
        return keys[k]

    faces = []
    nI = len(Vc)
    for L in loops:
        for v, pos in zip(L.vertices, L.positions):
            fixed_id(L.source, v, pos)
    for i, kind, j in pairs:
        P = loops[i]
        Q = iso_loops[j] if kind == "iso" else loops[j]
        if not orientation_agrees(P.positions, Q.positions):
            warnings += 1
            log.warning("fusion: loops of different orientation bridged near %s", P.positions.mean(axis=0))
        T = bridge_loops(P.positions, Q.positions)
        pid = np.array([fixed_id(P.source, v, x) for v, x in zip(P.vertices, P.positions)]) + nI
        if kind == "iso":
            qid = Q.vertices
        else:
            qid = np.array([fixed_id(Q.source, v, x) for v, x in zip(Q.vertices, Q.positions)]) + nI
        ids = np.concatenate([pid, qid])
        faces.append(ids[T])
    for c, i in enumerate(capped):
        P = loops[i]
        pid = np.array([fixed_id(P.source, v, x) for v, x in zip(P.vertices, P.positions)]) + nI
        centre = nI - len(capped) + c
        faces.append(np.array([(pid[k], pid[k - 1], centre) for k in range(len(pid))], np.int64))
    fixed_pos = np.asarray(fixed_pos, dtype=np.float64).reshape(-1, 3)
    JV = np.concatenate([Vc, fixed_pos])
    JF = np.concatenate([Fc] + faces) if (len(Fc) or faces) else np.zeros((0, 3), np.int64)
    return _Bridged(V=JV, F=JF, n_iso=nI, keys=keys, n_bridge=len(JF) - len(Fc), seam_edge=edge, fans=fans,
                    unmatched_preserved_loops=int(len(loops) - len(matched_pres) - len(capped)),
                    unmatched_iso_loops=unmatched_iso, orientation_warnings=warnings, capped_loops=len(capped))


def _bridge_without_crossings(Vc, Fc, loops, h, params):
    """Bridge the seams (:func:`bridge_seams`), cutting the isosurface back where a bridge crosses it.

    A bridge strip must not pass through the isosurface, nor through the fan closing a hole no
    seam claims (where the cut loop recedes far from its seam, or a second hole opens beside
    it): the isosurface around what it crosses is cut away too and the loops bridged again, at
    most ``params.bridge_recuts`` times. A recut stands only if every seam loop is still bridged
    and the junction stays edge-manifold (the remeshing needs it): without that check,
    CesiumMan's left leg replaced by itself, recut twice, bridges into a non-manifold junction
    that stays unremeshed (p05 2.3 degrees).

    Parameters
    ----------
    Vc : (k, 3) float array, Fc : (q, 3) int array
        The cut isosurface.
    loops : list of Loop
        Seam loops of the cluster.
    h : float
        Voxel (same units as the meshes).
    params : FusionParams

    Returns
    -------
    bridge : _Bridged
    recuts : int
        Recuts that stood.
    rejected : bool
        Whether a recut was tried and undone.
    """
    bridge = bridge_seams(Vc, Fc, loops, h, params.cut_voxels)
    recuts, rejected = 0, False
    for _ in range(params.bridge_recuts):
        JV, JF, nb, fans = bridge.V, bridge.F, bridge.n_bridge, bridge.fans
        if nb == 0 or len(Fc) == 0:
            break
        hits = intersecting_face_pairs(JV, JF, len(JF) - nb + np.arange(nb))
        crossed = np.unique(hits[:, 1][hits[:, 1] < len(JF) - nb])
        if len(crossed) == 0:
            break
        marked = [JV[v] for v in np.unique(JF[crossed].ravel()) if v not in fans]
        marked += [P for v in np.unique(JF[crossed].ravel()) if v in fans for P in fans[v]]
        near = np.isin(_position_keys(Vc), _position_keys(np.asarray(marked)))
        Vc2, Fc2, _ = remove_unreferenced(Vc, Fc[~near[Fc].any(axis=1)])
        again = bridge_seams(Vc2, Fc2, loops, h, params.cut_voxels)
        if (len(again.F) == 0 or again.without_partner > bridge.without_partner
                or not is_edge_manifold(again.F)):
            rejected = True
            break
        Vc, Fc, bridge = Vc2, Fc2, again
        recuts += 1
    return bridge, recuts, rejected


@dataclass(frozen=True)
class _RemeshJob:
    """What every remeshing attempt of one junction shares.

    Attributes
    ----------
    V : (k, 3) float64, F : (q, 3) int64
        The bridged junction (the reference), edge-manifold.
    fixed : (s,) int64
        Its seam vertices, kept exactly.
    target : float
        Target edge length.
    tol : float
        How far the junction may stray from the reference (0: plain remeshing only).
    h : float
        Voxel.
    forbidden : (e, 2) int64
        Edges of preserved faces between seam vertices (never created by a flip).
    corners : (c, 3) float64 or None
        Input vertices on the blended surface, kept by the shape-keeping path.
    targets : (t, 3) float64
        Input vertices junction vertices may snap to.
    pres, surfaces, inputs_fields, params
        As in :func:`junction_for_cluster`.
    clear : callable or None
        Points ``(k, 3)`` -> ``(k,) bool``: outside the kept closed parts' clearance
        (:func:`_clear_of_parts`); None where no part is near.
    input_dihedral : float or None
        Degrees: how much the replaced input surface creases (:func:`_replaced_dihedral`).
    """

    V: np.ndarray
    F: np.ndarray
    fixed: np.ndarray
    target: float
    tol: float
    h: float
    forbidden: np.ndarray
    corners: np.ndarray | None
    targets: np.ndarray
    pres: list
    surfaces: list
    inputs_fields: dict
    params: object
    clear: object = None
    input_dihedral: float | None = None


def _remesh_attempt(job, feature_tol, smoothed=False):
    """Remesh (keeping what strays farther than ``feature_tol``; 0: plain), smooth, improve
    (a collapse never moves the shape by more than ``job.tol``, on either path). ``smoothed``
    (a plain remeshing): smoothed ``plain_taubin_iterations`` times and pulled onto the inputs
    only where they agree (:func:`project_to_inputs`), the field's shape without the creases
    of a union.

    Returns
    -------
    U : (p, 3) float64, G : (g, 3) int64
        ``U[:len(job.fixed)] == job.V[job.fixed]``.
    nfeat : int
        Feature vertices kept after the seam vertices.
    """
    params, h, forb = job.params, job.h, job.forbidden
    pres, surfaces, inputs_fields = job.pres, job.surfaces, job.inputs_fields
    U, G, nfix, (RV, RF) = remesh_keeping_features(job.V, job.F, job.fixed, job.target, params.remesh_iterations,
                                                   feature_tol, params.feature_rounds, points=job.corners,
                                                   points_tol=0.1 * h, max_insert=3.0 * h,
                                                   refine_rounds=params.refine_rounds,
                                                   min_edge=params.refine_min_edge * job.target, forbidden=forb)
    smoothing = params.plain_taubin_iterations if smoothed else params.taubin_iterations
    U = smooth_interior(U, G, np.arange(nfix), iterations=smoothing)
    U = project_to_inputs(U, nfix, pres, surfaces, inputs_fields, h, params.project_voxels, job.clear,
                          agreeing=smoothed)
    G = flip_to_improve_angles(U, G, forbidden=forb)
    U = relocate_poor_vertices(U, G, nfix, surface=(RV, RF))
    G = flip_to_improve_angles(U, G, forbidden=forb)
    if params.collapse_poor:
        U, G = collapse_to_improve_angles(U, G, nfix, max_deviation=job.tol, forbidden=forb)
        G = flip_to_improve_angles(U, G, forbidden=forb)
        U = relocate_poor_vertices(U, G, nfix, surface=(RV, RF))
        G = flip_to_improve_angles(U, G, forbidden=forb)
    if len(job.targets):
        U = snap_to_points(U, G, nfix, job.targets, max_dist=0.5 * job.target, min_angle=params.min_angle_p05)
        G = flip_to_improve_angles(U, G, forbidden=forb)
    if feature_tol > 0:
        # the quality moves above slide vertices along the reference, whose bridge
        # strips chord across a voxel or two: back onto the inputs where they agree
        U = project_to_inputs(U, nfix, pres, surfaces, inputs_fields, h, params.project_voxels, job.clear)
    # folds smoothed open only where that keeps the shape-keeping junction's tolerance
    U, _ = untangle(U, G, nfix, max_move=params.untangle_move * feature_tol if feature_tol > 0 else None)
    return _separate_coincident(U, G, len(job.fixed)), G, nfix - len(job.fixed)


def _remesh_choosing_fidelity(job, info):
    """The shape-keeping remeshing, or a looser or plain one where it makes slivers.

    Fidelity never at the price of slivers: the features stand only while the junction's
    5th-percentile minimum angle stays at ``min_angle_p05``, or is no worse than the plain
    remeshing's. Where the plain remeshing loses more of the shape than a looser tolerance
    (``fidelity_relax``) allows, that looser tolerance (fewer kept features) is tried first;
    keeping less, it may cost little. Folds choose within a bound: a folded shape-keeping
    junction gives way to a plain one that folds less only where that strays at most
    ``fold_free_deviation`` times as far (``folds_avoided`` in ``info``; the fold-free plain
    junction would cost RiggedFigure's left leg, replaced by itself, 1.3% of the diagonal
    against 0.36%). Creases choose: where the kept features crease the junction (the 95th
    percentile of its dihedral angles) more than ``crease_ratio`` times the replaced input
    surface does (``job.input_dihedral``), the plain junction is taken if it creases less
    (``creases_avoided`` in ``info``, degrees). Neither takes a plain junction that misses
    ``min_angle_p05`` where the shape-keeping one meets it: that would trade one gate for
    another.

    ``fidelity``, ``fidelity_tolerance`` and, after a miss, ``plain_deviation`` and
    ``fidelity_retries`` are written into ``info`` as each is decided, so that a remeshing
    failure part-way leaves them in the report.

    Returns
    -------
    U : (p, 3) float64, G : (g, 3) int64, nfeat : int
        As :func:`_remesh_attempt`.
    """

    params, tol = job.params, job.tol
    U, G, nfeat = _remesh_attempt(job, tol)
    info["fidelity"] = bool(tol > 0)
    info["fidelity_tolerance"] = float(tol)
    angle = _angle_p05(U, G)
    plain = None  # the plain remeshing and how far it strays from the reference, made once when asked

    def plain_remeshing():
        nonlocal plain
        if plain is None:
            U0, G0, _ = _remesh_attempt(job, 0.0)
            plain = U0, G0, _strays(job.V, U0, G0)
        return plain

    if tol > 0 and angle < params.min_angle_p05:
        U0, G0, lost = plain_remeshing()
        plain_angle = _angle_p05(U0, G0)
        info["plain_deviation"] = float(lost)
        chosen = False
        for loose in [tol * f for f in params.fidelity_relax]:
            if lost <= loose:
                break
            U1, G1, n1 = _remesh_attempt(job, loose)
            a1 = _angle_p05(U1, G1)
            info.setdefault("fidelity_retries", []).append(
                {"tolerance": float(loose), "junction_min_angle_p05": float(a1)})
            if a1 >= params.min_angle_p05 and a1 >= plain_angle - params.relax_max_angle_loss:
                U, G, nfeat, chosen = U1, G1, n1, True
                info["fidelity_tolerance"] = float(loose)
                break
        if not chosen and plain_angle > angle:
            U, G, nfeat = U0, G0, 0
            info["fidelity"] = False
            info["fidelity_tolerance"] = 0.0
    def angles_kept(U0, G0):  # the plain junction meets the angle bound, or misses it no more
        return _angle_p05(U0, G0) >= min(params.min_angle_p05, _angle_p05(U, G))

    if info["fidelity"] and params.fold_free_deviation > 0:
        folds = _folds(U, G)
        if folds:
            U0, G0, lost = plain_remeshing()
            if (_folds(U0, G0) < folds and lost <= params.fold_free_deviation * max(_strays(job.V, U, G), tol)
                    and angles_kept(U0, G0)):
                U, G, nfeat = U0, G0, 0
                info.update(fidelity=False, fidelity_tolerance=0.0, folds_avoided=int(folds))
    if params.crease_ratio > 0 and job.input_dihedral is not None:
        bound = params.crease_ratio * job.input_dihedral
        creased = _dihedral_p95(U, G)
        if info["fidelity"] and creased > bound:
            U0, G0, _ = plain_remeshing()
            plain_creased = _dihedral_p95(U0, G0)
            if plain_creased < creased and angles_kept(U0, G0):
                U, G, nfeat = U0, G0, 0
                info.update(fidelity=False, fidelity_tolerance=0.0, creases_avoided=creased)
                creased = plain_creased
        # a junction that still creases more than the input: the smoothed plain one, where it
        # creases less, keeps the angles and folds no more
        if creased > bound:
            U1, G1, _ = _remesh_attempt(job, 0.0, smoothed=True)
            if _dihedral_p95(U1, G1) < creased and angles_kept(U1, G1) and _folds(U1, G1) <= _folds(U, G):
                U, G, nfeat = U1, G1, 0
                info.update(fidelity=False, fidelity_tolerance=0.0, creases_smoothed=creased)
    return U, G, nfeat


def _strays(R, U, G):
    """How far the reference vertices ``R`` ``(n, 3)`` lie from the surface ``(U, G)`` at most."""
    import igl

    return float(np.sqrt(igl.point_mesh_squared_distance(R, U, G)[0]).max())


#: Neighbouring faces whose normals turn more than this (degrees) fold onto each other.
FOLD_ANGLE = 150.0


def _folds(V, F):
    """Folds of a junction surface: crossing face pairs, and neighbouring faces whose normals
    turn past :data:`FOLD_ANGLE`."""
    return int(len(intersecting_face_pairs(V, F)) + np.count_nonzero(dihedral_angles(V, F) > FOLD_ANGLE))


def _remesh_bridged(bridge, grid, pres, surfaces, preserved, inputs_fields, actions, params, band, field3,
                    local_edge, junction_masks, diagonal, floor3=None):
    """Remesh the bridged junction with the seam vertices fixed (unused ones dropped first).

    The junction is kept as bridged where it is not edge-manifold or the remeshing fails
    (remeshing is an improvement, never a reason to fail).

    Returns
    -------
    JV : (k, 3) float64, JF : (q, 3) int64
        Seam vertices first.
    fixed_keys : list of (input, welded vertex)
        Of ``JV[:len(fixed_keys)]``.
    info : dict
        ``fidelity``, ``fidelity_tolerance``, ``plain_deviation`` and ``fidelity_retries``
        (:func:`_remesh_choosing_fidelity`), ``self_intersections``, ``feature_vertices`` and
        ``remeshed``.
    """
    h = grid.voxel
    nI, keys, edge = bridge.n_iso, bridge.keys, bridge.seam_edge
    JV, JF, old = remove_unreferenced(bridge.V, bridge.F)
    JF = flip_doubled_edges(JV, JF)  # a pinched seam bridged from both sides of its pinch
    isfixed = old >= nI
    fixed_keys = {v: k for k, v in keys.items()}
    info: dict = {}
    fkeys = None
    if len(JF) and is_edge_manifold(JF):
        fx = np.flatnonzero(isfixed)
        # fine enough for the shape, never much finer than the fixed seam edges (slivers)
        target = params.target_edge_factor * min(edge, local_edge if local_edge > 0 else edge)
        target = max(target, 0.5 * edge)
        # how far the junction may stray from the reference: a fraction of a voxel, and of the
        # character where the voxel is a large part of it (low-poly characters)
        tol = params.fidelity_voxels * h
        if diagonal > 0 and params.fidelity_diagonal > 0:
            tol = min(tol, params.fidelity_diagonal * diagonal)
        fid_to_final = {int(old[v] - nI): k for k, v in enumerate(fx)}
        forb = _preserved_edges_between(pres, preserved, keys, fid_to_final)
        try:
            replaced = _replaced_input_vertices(pres, inputs_fields, junction_masks, preserved, grid)
            clear = None if floor3 is None else partial(_clear_of_parts, grid=grid, floor3=floor3)
            if clear is not None:  # input vertices under a kept part are neither targets nor corners
                replaced = replaced[clear(replaced)]
            targets = _surface_input_vertices(replaced, grid, field3, h) if params.snap_input_vertices else replaced[:0]
            corners = None
            if params.keep_input_corners and tol > 0:
                corners = _input_vertices_on_surface(replaced, pres, surfaces, inputs_fields, actions, band, 0.1 * h)
            job = _RemeshJob(V=JV, F=JF, fixed=fx, target=target, tol=tol, h=h, forbidden=forb, corners=corners,
                             targets=targets, pres=pres, surfaces=surfaces, inputs_fields=inputs_fields,
                             params=params, clear=clear,
                             input_dihedral=_replaced_dihedral(pres, inputs_fields, junction_masks, grid))
            U, G, nfeat = _remesh_choosing_fidelity(job, info)
            info["self_intersections"] = int(len(intersecting_face_pairs(U, G)))
            info["feature_vertices"] = int(nfeat)
            fkeys = [fixed_keys[int(old[v] - nI)] for v in fx]
            JV, JF = U, G
            info["remeshed"] = True
        except Exception as exc:  # remeshing is an improvement, never a reason to fail
            log.warning("fusion: junction remeshing failed (%s); keeping the bridged mesh", exc)
            info["remeshed"] = False
    else:
        info["remeshed"] = False
    if fkeys is None:
        order = np.concatenate([np.flatnonzero(isfixed), np.flatnonzero(~isfixed)])
        inv = np.empty_like(order)
        inv[order] = np.arange(len(order))
        JV, JF = JV[order], inv[JF]
        fkeys = [fixed_keys[int(old[v] - nI)] for v in np.flatnonzero(isfixed)]
    return JV, JF, fkeys, info


@dataclass(frozen=True)
class ClusterJunction:
    """The junction surface of one cluster.

    Attributes
    ----------
    V : (k, 3) float64
        Junction vertices, seam vertices first (bit-identical to the inputs' welded positions).
    F : (q, 3) int64
        Junction faces over ``V``.
    fixed_keys : list of (input, welded vertex)
        Source of each seam vertex ``V[:len(fixed_keys)]``.
    info : dict
        ``iso_faces``, ``unmatched_preserved_loops``, ``unmatched_iso_loops``,
        ``orientation_warnings``, ``bridge_recuts`` and ``bridge_recuts_rejected`` (when
        non-zero), then the remeshing's entries (:func:`_remesh_bridged`).
    field : (nx, ny, nz) float64
        The blended field on the cluster's grid.
    timings : dict
        Seconds: ``blend``, ``isosurface``, ``cut_bridge``, ``remesh``.
    """

    V: np.ndarray
    F: np.ndarray
    fixed_keys: list
    info: dict
    field: np.ndarray
    timings: dict


def junction_for_cluster(grid, pres, surfaces, preserved, loops, inputs_fields, actions, params, band,
                         local_edge=0.0, junction_masks=None, diagonal=0.0, floor=None) -> ClusterJunction:
    """Isosurface, cut, bridges and remesh of one cluster.

    Parameters
    ----------
    grid : Grid
        The cluster's grid (:func:`.seams.cluster_grid`).
    pres : list of Presence
    surfaces : list of (f_i, 3) int arrays
        Per input, the welded faces its field is computed from.
    preserved : list of (m_i,) bool arrays
        Per input, welded faces the output keeps (preserved or copied): they cut the
        isosurface and their boundary gives the seams.
    loops : list of Loop
        Seam loops in the cluster.
    inputs_fields : dict
        Input -> ``(d, p)``, signed distance and presence at the grid's samples, ``(N,)`` each.
    actions : sequence of FusionAction
    params : FusionParams
    band : float
        Distances are exact within ``band`` of a surface (same units as the meshes).
    local_edge : float
        Mean edge of the input faces the junction replaces (:func:`.seams.local_edge_length`).
    junction_masks : list of (m_i,) bool arrays
        Per input, the welded faces the junction replaces.
    diagonal : float
        Smallest input's bounding-box diagonal (0: no diagonal rule).
    floor : (grid.size,) float array or None
        A lower bound of the blended field (the kept closed parts the junction goes around).

    Returns
    -------
    ClusterJunction
    """
    t0 = time.perf_counter()
    field = _field_for_cluster(grid.size, inputs_fields, actions, band)
    field3 = (field if floor is None else np.maximum(field, floor)).reshape(grid.shape)
    floor3 = None if floor is None else floor.reshape(grid.shape)
    t_blend = time.perf_counter() - t0
    t0 = time.perf_counter()
    Vi, Fi = isosurface(field3, grid.origin, grid.voxel)
    t_iso = time.perf_counter() - t0

    t0 = time.perf_counter()
    h = grid.voxel
    Vc, Fc = _cut_isosurface(Vi, Fi, pres, preserved, params.cut_voxels * h)
    bridge, recuts, rejected = _bridge_without_crossings(Vc, Fc, loops, h, params)
    info = {"iso_faces": int(len(Fi)), "unmatched_preserved_loops": bridge.unmatched_preserved_loops,
            "unmatched_iso_loops": bridge.unmatched_iso_loops, "orientation_warnings": bridge.orientation_warnings,
            "capped_loops": bridge.capped_loops}
    if recuts:
        info["bridge_recuts"] = recuts
    if rejected:
        info["bridge_recuts_rejected"] = 1
    t_bridge = time.perf_counter() - t0

    t0 = time.perf_counter()
    JV, JF, fkeys, remesh_info = _remesh_bridged(bridge, grid, pres, surfaces, preserved, inputs_fields, actions,
                                                 params, band, field3, local_edge, junction_masks, diagonal,
                                                 floor3)
    info.update(remesh_info)
    t_remesh = time.perf_counter() - t0
    return ClusterJunction(V=JV, F=JF, fixed_keys=fkeys, info=info, field=field3,
                           timings={"blend": t_blend, "isosurface": t_iso, "cut_bridge": t_bridge,
                                    "remesh": t_remesh})
