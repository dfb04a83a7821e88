"""``fuse_surfaces``: the new surface M_R = M'_0 + M'_1 + M_J (PIPELINE.md section 3).

Stages, each a function of :mod:`rigmix.fusion`:

1. presence per input vertex, secondary components, preserved faces (:mod:`.presence`);
2. for attach, faces of one input inside or against the present part of the other stop being
   preserved (the union must cut through them);
3. junction clusters: boxes around the faces that are neither preserved nor absent;
4. local signed distance fields and their blend per action (:mod:`.fields`);
5. isosurface, cut by the preserved faces, loops bridged, remeshed and smoothed
   (:mod:`.junction`, :mod:`.remesh`);
6. assembly: preserved faces copied bit-identically, junction vertices appended.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np

from ..errors import InputError
from .fields import Grid, blend_attach, blend_cap, blend_replace, get_backend, prepare_surface
from .junction import (
    Loop,
    boundary_loops,
    bridge_loops,
    clip_mesh,
    isosurface,
    keep_components_touching,
    match_loops,
    orientation_agrees,
    remove_unreferenced,
)
from .meshutil import average_edge_length, boundary_halfedges, edge_counts, face_adjacency, undirected_edges
from .presence import Presence, compute_presence
from .remesh import flip_to_improve_angles, is_edge_manifold, relocate_poor_vertices, snap_to_points, remesh_junction, smooth_interior
from .report import mesh_report

log = logging.getLogger(__name__)

__all__ = ["FusionInput", "FusionAction", "FusionParams", "FusedSurface", "fuse_surfaces"]


@dataclass(frozen=True)
class FusionInput:
    """One input character's surface contribution, after positioning (rest pose).

    Attributes
    ----------
    V : (n, 3) float64
        Split vertices of all its skinned meshes concatenated.
    F : (m, 3) int64
    W : (n, J) float64
        Dense skin weights.
    used : (J,) bool
        Joints of this character kept in the output skeleton.
    mesh_of_vertex : (n,) int64, optional
        Which source mesh (primitive) each vertex comes from.
    uvs : (n, 2) float64, optional
    normals : (n, 3) float64, optional
    colors : (n, 4) float64, optional
        Linear RGBA (textures baked to vertex colours by the caller), interpolated at the junction.
    name : str
    """

    V: np.ndarray
    F: np.ndarray
    W: np.ndarray
    used: np.ndarray
    mesh_of_vertex: np.ndarray | None = None
    uvs: np.ndarray | None = None
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    name: str = ""


@dataclass(frozen=True)
class FusionAction:
    """Inputs ``a`` and ``b`` meet: ``replace`` (presence-weighted blend) or ``attach`` (union)."""

    kind: Literal["replace", "attach"]
    a: int
    b: int


@dataclass(frozen=True)
class FusionParams:
    """Parameters of the fusion (defaults: PIPELINE.md section 3, see each note).

    Attributes
    ----------
    snap, smooth_iterations, smooth_alpha : presence snapping and smoothing (0.02, 10, 0.8).
    preserve_threshold : face presence for a preserved face (prototype 0.999).
    morphology_rounds : opening-closing rounds on the face adjacency (2).
    secondary_variance : presence variance under which a component is secondary (0.04).
    voxel_factor : voxel = voxel_factor x smallest average edge length (0.8) before refinement.
    min_voxels_across : the voxel is refined until this many span the junction (its second
        largest extent).
    margin_voxels : the grid reaches this many voxels beyond the junction faces (10).
    band_voxels : exact distances within this many voxels of a surface, clamped beyond.
    max_voxels : cap on samples per grid (the voxel grows to respect it).
    cut_voxels : isosurface parts closer than this to a preserved face are cut away.
    attach_conflict_voxels : for attach, faces this close to the other's present part are blended.
    remesh_iterations, target_edge_factor : junction remeshing; target = factor x the smaller
        of the mean preserved boundary edge and the mean edge of the input faces the junction
        replaces. The prototype's 0.8 chords off the creases of low-poly game meshes (measured:
        up to 0.86% of the bounding-box diagonal on CesiumMan self-compositions); 0.5 keeps
        them under 0.5%.
    taubin_iterations : smoothing of the remeshed junction interior.
    project_voxels : junction vertices are then pulled at most this many voxels towards the
        presence-weighted closest input points (0 disables).
    min_seam_wedge : degrees; preserved faces around a seam vertex that leaves the junction a
        thinner wedge than this join the junction (no good triangle fits such a wedge).
    snap_input_vertices : junction vertices move onto the nearby vertices of the replaced input
        faces that lie on the blended surface (within a quarter voxel): corners of low-poly
        inputs survive the remeshing.
    min_island_faces : preserved parts bordering a junction with fewer faces join it (specks
        left by the presence pattern have no isosurface hole to meet).
    backend : "numpy" (numpy + libigl) or "openvdb".
    keep_fields : keep the blended grids in the result (for ``dump_fields``).
    """

    snap: float = 0.02
    smooth_iterations: int = 10
    smooth_alpha: float = 0.8
    preserve_threshold: float = 0.999
    morphology_rounds: int = 2
    secondary_variance: float = 0.04
    voxel_factor: float = 0.8
    min_voxels_across: int = 32
    margin_voxels: float = 10.0
    band_voxels: float = 8.0
    max_voxels: int = 4_000_000
    cut_voxels: float = 1.0
    attach_conflict_voxels: float = 2.0
    remesh_iterations: int = 5
    target_edge_factor: float = 0.5
    taubin_iterations: int = 3
    project_voxels: float = 1.0
    min_seam_wedge: float = 60.0
    min_island_faces: int = 24
    snap_input_vertices: bool = True
    backend: str = "numpy"
    keep_fields: bool = False


@dataclass(frozen=True)
class FusedSurface:
    """The fused rest surface M_R.

    Attributes
    ----------
    V : (N, 3) float64
        Output vertices: preserved split vertices of each input (in input order, then source
        order), then junction vertices.
    F : (M, 3) int64
        Preserved faces first (input order, source order), then junction faces.
    origin_input, origin_vertex : (N,) int64
        Source input and split vertex of each output vertex; ``-1`` for junction vertices.
    face_origin_input, face_origin_face : (M,) int64
        Source of each face; ``-1`` for junction faces.
    junction_faces : (M,) bool
    preserved : tuple of (m_i,) bool
        Per input, its faces copied into the output.
    presence : tuple of (n_i,) float64
        Per input, smoothed presence per split vertex.
    mesh_of_vertex : (N,) int64
        Source mesh of the preserved vertices, ``-1`` at the junction.
    uvs, normals, colors : (N, 2), (N, 3), (N, 4) float64 or None
        Copied on preserved vertices (bit-identical); junction normals from the surface, UVs 0,
        colours interpolated from the closest input points (presence-weighted).
    junction_sources : tuple of dict
        Per input, for each junction vertex: ``face`` (split face of the closest point),
        ``bary`` (barycentric, (k, 3)), ``distance``, ``presence`` at that point.
    fields : tuple of (name, Grid, array)
        Blended fields (only with ``FusionParams.keep_fields``).
    report : dict
        ``mesh`` (vertices, faces, non_manifold_edges, new_non_manifold_edges,
        junction_boundary_edges, junction_min_angle_p05, junction_faces, unmatched_loops),
        ``fields`` (voxel_size, voxels, backend, grids), ``timings`` (seconds per stage).
    """

    V: np.ndarray
    F: np.ndarray
    origin_input: np.ndarray
    origin_vertex: np.ndarray
    face_origin_input: np.ndarray
    face_origin_face: np.ndarray
    junction_faces: np.ndarray
    preserved: tuple
    presence: tuple
    mesh_of_vertex: np.ndarray
    uvs: np.ndarray | None
    normals: np.ndarray | None
    colors: np.ndarray | None
    junction_sources: tuple = ()
    fields: tuple = ()
    report: dict = field(default_factory=dict)


# --------------------------------------------------------------------------------------------


def _check_inputs(inputs, actions):
    for i, x in enumerate(inputs):
        V, F, W = np.asarray(x.V), np.asarray(x.F), np.asarray(x.W)
        if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
            raise InputError(f"fusion: input {i} ({x.name!r}) needs V (n, 3) and F (m, 3)")
        if len(W) != len(V) or W.shape[1] != len(np.asarray(x.used)):
            raise InputError(f"fusion: input {i} ({x.name!r}) weights must be (n, J) with used (J,)")
        if len(F) and (F.min() < 0 or F.max() >= len(V)):
            raise InputError(f"fusion: input {i} ({x.name!r}) has face indices out of range")
    for a in actions:
        if a.kind not in ("replace", "attach"):
            raise InputError(f"fusion: action kind {a.kind!r}, expected 'replace' or 'attach'")
        if not (0 <= a.a < len(inputs) and 0 <= a.b < len(inputs)) or a.a == a.b:
            raise InputError(f"fusion: action {a} must name two different inputs")


def _attach_conflicts(pres: list[Presence], actions, h):
    """Preserved faces the fused surface must cut through or that it buries.

    attach: faces of either input near or inside the other's present part. replace: faces of
    one input buried inside the present part of the other (the rider's hips inside the horse):
    their seams would have no isosurface to meet. Faces on the other surface itself (a
    character composed with itself) are not buried.
    """
    import igl

    out = [p.preserved.copy() for p in pres]
    for act in actions:
        for x, y in ((act.a, act.b), (act.b, act.a)):
            Py = pres[y]
            fp = Py.p_welded[Py.welded.F].mean(axis=1)
            Fy = Py.welded.F[(fp >= 0.5) & ~Py.absent & ~Py.secondary]
            Px = pres[x]
            idx = np.flatnonzero(out[x] & ~Px.secondary)
            if len(Fy) == 0 or len(idx) == 0:
                continue
            Vx = Px.welded.V
            C = Vx[Px.welded.F[idx]].mean(axis=1)
            Vy = Py.welded.V
            d2, _, _ = igl.point_mesh_squared_distance(C, Vy, Fy)
            if act.kind == "attach":
                w = igl.fast_winding_number(Vy, Fy, C)
                hit = (d2 < (h * 2.0) ** 2) | (np.abs(w) > 0.5)
            else:
                # inside the other's whole surface, nearest to a present part of it, not on it
                Fall = prepare_surface(Vy, Py.welded.F[~Py.secondary])
                w = igl.fast_winding_number(Vy, Fall, C)
                d2a, fa, _ = igl.point_mesh_squared_distance(C, Vy, Fall)
                pa = Py.p_welded[Fall[fa]].mean(axis=1)
                hit = (w > 0.5) & (pa >= 0.5) & (d2a > (0.5 * h) ** 2)
            out[x][idx[hit]] = False
    return out


def _seam_components(P: Presence, preserved):
    """Face-connected components of the preserved faces that border the junction.

    Returns
    -------
    list of (k,) int64 arrays of face indices.
    """
    from scipy.sparse.csgraph import connected_components

    idx = np.flatnonzero(preserved & ~P.secondary)
    if len(idx) == 0:
        return []
    A = face_adjacency(P.welded.F)[idx][:, idx]
    _, lab = connected_components(A, directed=False)
    B = boundary_halfedges(P.welded.F[idx])
    if len(B) == 0:
        return []
    uE, cnt = edge_counts(P.welded.F)
    n = len(P.welded.V) + 1
    key_all = uE[:, 0] * n + uE[:, 1]
    Bs = np.sort(B, axis=1)
    pos = np.clip(np.searchsorted(key_all, Bs[:, 0] * n + Bs[:, 1]), 0, len(cnt) - 1)
    seam_v = np.unique(B[cnt[pos] >= 2].ravel())
    on_seam = np.zeros(len(P.welded.V), bool)
    on_seam[seam_v] = True
    comps = []
    for c in range(lab.max() + 1):
        f = idx[lab == c]
        if on_seam[P.welded.F[f]].any():
            comps.append(f)
    return comps


def _pinched(F):
    """``(m,)`` bool: faces at a vertex where the boundary passes more than once."""
    B = boundary_halfedges(F)
    if len(B) == 0:
        return np.zeros(len(F), bool)
    n = int(np.max(F)) + 1
    cnt = np.bincount(B[:, 0], minlength=n)
    return (cnt[F] > 1).any(axis=1)


def _unpinch_preserved(pres: list[Presence], preserved, rounds=3):
    """Un-preserve the faces at seam vertices the preserved boundary visits twice.

    Two seam loops through one vertex would both be bridged from it and give an edge of three
    or four faces.
    """
    out = [m.copy() for m in preserved]
    for i, P in enumerate(pres):
        for _ in range(rounds):
            idx = np.flatnonzero(out[i])
            if len(idx) == 0:
                break
            bad = _pinched(P.welded.F[idx])
            if not bad.any():
                break
            out[i][idx[bad]] = False
    return out


def _drop_specks(pres: list[Presence], preserved, min_faces):
    """Un-preserve preserved parts bordering a junction with fewer than ``min_faces`` faces
    (and under 2% of the input's faces: a low-poly limb of a dozen faces is no speck)."""
    out = [m.copy() for m in preserved]
    for i, P in enumerate(pres):
        limit = min(min_faces, 0.02 * len(P.welded.F))
        for f in _seam_components(P, preserved[i]):
            if len(f) < limit:
                out[i][f] = False
    return out


def _separate_seams(pres: list[Presence], preserved, delta):
    """Un-preserve faces closer than ``delta`` to another preserved part bordering a junction.

    Where two preserved parts (of two inputs, or two parts of one input on either side of a
    junction) come closer than the isosurface cut leaves room for (the underside of a limb
    against the body), the cut isosurface would pinch there and its boundary loops merge,
    which no loop-to-loop bridge can close; widening the junction keeps every seam its own loop.
    """
    import igl

    comps = [(i, f) for i, P in enumerate(pres) for f in _seam_components(P, preserved[i])]
    out = [m.copy() for m in preserved]
    if len(comps) < 2:
        return out
    for k, (i, fa) in enumerate(comps):
        Pi = pres[i]
        Pt = Pi.welded.V[Pi.welded.F[fa]]  # (a, 3, 3)
        hit = np.zeros(len(fa), bool)
        for j in range(len(pres)):
            other = [f for (jj, f), kk in zip(comps, range(len(comps))) if jj == j and kk != k]
            if not other:
                continue
            Fj = pres[j].welded.F[np.concatenate(other)]
            Vj = pres[j].welded.V
            lo = Vj[Fj].reshape(-1, 3).min(axis=0) - delta
            hi = Vj[Fj].reshape(-1, 3).max(axis=0) + delta
            near = np.all((Pt.max(axis=1) >= lo) & (Pt.min(axis=1) <= hi), axis=1) & ~hit
            if not near.any():
                continue
            d2, _, _ = igl.point_mesh_squared_distance(Pt[near].reshape(-1, 3), Vj, Fj)
            hit[np.flatnonzero(near)[(d2.reshape(-1, 3) < delta * delta).any(axis=1)]] = True
        out[i][fa[hit]] = False
    return out


def _open_notches(P: Presence, preserved, *, min_wedge=60.0, rounds=3):
    """Un-preserve the faces around seam vertices where the junction would be a thin wedge.

    At a vertex of the preserved boundary, the junction gets what the preserved faces leave of
    the angle around it; below ``min_wedge`` degrees no triangulation reaches a good minimum
    angle there, so the preserved faces at that vertex join the junction.
    """
    Fw = P.welded.F
    ok = ~P.absent | preserved
    ang = np.degrees(_corner_angles(P.welded.V, Fw))
    out = preserved.copy()
    n = len(P.welded.V)
    for _ in range(rounds):
        tot = np.bincount(Fw[ok].ravel(), weights=ang[ok].ravel(), minlength=n)
        kept = np.bincount(Fw[out].ravel(), weights=ang[out].ravel(), minlength=n)
        B = boundary_halfedges(Fw[out])
        if len(B) == 0:
            break
        seam = np.zeros(n, bool)
        seam[B.ravel()] = True
        bad = seam & (tot - kept < min_wedge) & (tot - kept > 1e-9)
        if not bad.any():
            break
        out &= ~bad[Fw].any(axis=1)
    return out


def _corner_angles(V, F):
    """Interior angle at each corner, ``(m, 3)`` radians (0 for degenerate corners)."""
    P = V[F]
    out = np.zeros(F.shape)
    for c in range(3):
        u = P[:, (c + 1) % 3] - P[:, c]
        w = P[:, (c + 2) % 3] - P[:, c]
        nu = np.linalg.norm(u, axis=1)
        nw = np.linalg.norm(w, axis=1)
        cos = np.einsum("ij,ij->i", u, w) / np.maximum(nu * nw, 1e-300)
        out[:, c] = np.where((nu > 0) & (nw > 0), np.arccos(np.clip(cos, -1, 1)), 0.0)
    return out


def _clusters(pres, junction, margin):
    """Boxes ``(lo, hi)`` around the junction faces, overlapping boxes merged."""
    boxes = []
    for i, P in enumerate(pres):
        J = np.flatnonzero(junction[i])
        if len(J) == 0:
            continue
        A = face_adjacency(P.welded.F)[J][:, J]
        from scipy.sparse.csgraph import connected_components

        _, lab = connected_components(A, directed=False)
        pts = P.welded.V[P.welded.F[J]]
        for c in range(lab.max() + 1):
            q = pts[lab == c].reshape(-1, 3)
            boxes.append([q.min(axis=0), q.max(axis=0)])
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for a in range(len(boxes)):
            for b in range(a + 1, len(boxes)):
                la, ha = boxes[a]
                lb, hb = boxes[b]
                if np.all(la - margin <= hb + margin) and np.all(lb - margin <= ha + margin):
                    boxes[a] = [np.minimum(la, lb), np.maximum(ha, hb)]
                    boxes.pop(b)
                    merged = True
                    break
            if merged:
                break
    return boxes


def _grid_for(lo, hi, h0, params):
    ext = hi - lo
    across = np.sort(ext)[1]
    h = min(h0, across / max(params.min_voxels_across, 1)) if across > 0 else h0
    for _ in range(20):
        margin = max(params.margin_voxels * h, (params.cut_voxels + 4) * h)
        glo = lo - margin
        shape = tuple(int(x) for x in np.ceil((hi + margin - glo) / h) + 1)
        if np.prod(shape) <= params.max_voxels:
            break
        h *= (np.prod(shape) / params.max_voxels) ** (1 / 3) * 1.02
    return Grid(glo, float(h), shape)


def _preserved_loops(P: Presence, preserved, source):
    """Closed boundary loops of the preserved faces that run through the input's interior."""
    Fw = P.welded.F
    B = boundary_halfedges(Fw[preserved])
    if len(B) == 0:
        return [], 0
    uE, cnt = edge_counts(Fw)
    # keep the half-edges whose edge has other faces in the input (a seam, not an open border)
    key_all = uE[:, 0] * (len(P.welded.V) + 1) + uE[:, 1]
    Bs = np.sort(B, axis=1)
    key = Bs[:, 0] * (len(P.welded.V) + 1) + Bs[:, 1]
    pos = np.searchsorted(key_all, key)
    interior = cnt[np.clip(pos, 0, len(cnt) - 1)] >= 2
    loops, chains = boundary_loops(P.welded.V, None, source, halfedges=B[interior])
    return loops, int(sum(len(c) - 1 for c in chains))


def _select_faces(pres, junction, grid):
    """Fallback junction: each input's junction faces in ``grid`` where it is the most present.

    A face is kept from input ``i`` when its mean presence is above 0.5 (exactly 0.5: only for
    the first input), so a character composed with itself gets each face exactly once.
    """
    out = []
    for i, P in enumerate(pres):
        T = P.welded.F
        c = P.welded.V[T].mean(axis=1)
        inside = np.all((c >= grid.origin) & (c <= grid.upper), axis=1)
        fp = P.p_welded[T].mean(axis=1)
        keep = (fp > 0.5) | ((fp == 0.5) & (i == 0))
        out.append(junction[i] & inside & keep)
    return out


def _local_edge(pres, junction, grid):
    """Mean edge length of the input faces replaced by the junction inside ``grid``."""
    lens = []
    for i, P in enumerate(pres):
        T = P.welded.F[junction[i]]
        if len(T) == 0:
            continue
        c = P.welded.V[T].mean(axis=1)
        T = T[np.all((c >= grid.origin) & (c <= grid.upper), axis=1)]
        E = np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]])
        lens.append(np.linalg.norm(P.welded.V[E[:, 0]] - P.welded.V[E[:, 1]], axis=1))
    return float(np.concatenate(lens).mean()) if lens else 0.0


def _field_for_cluster(grid, inputs_fields, actions, band):
    """Blend the per-input fields on one grid: dominant action per voxel."""
    involved = [k for k, a in enumerate(actions) if a.a in inputs_fields and a.b in inputs_fields]
    if not involved:
        vals = [blend_cap(d, p, band=band) for d, p in inputs_fields.values()]
        return np.min(np.stack(vals), axis=0)
    best = np.full(grid.size, np.inf)
    out = np.full(grid.size, band)
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


def _project_to_inputs(U, nfixed, pres, surfaces, inputs_fields, h, max_voxels):
    """Pull free junction vertices onto the presence-weighted average of their closest points.

    The isosurface is only accurate to a fraction of a voxel at creases; where the inputs agree
    (a character composed with itself) this puts the junction back on the input surface. Moves
    are limited to ``max_voxels`` voxels so that a wide blend between different shapes keeps
    the field's shape.
    """
    import igl

    if max_voxels <= 0 or len(U) <= nfixed:
        return U
    Q = U[nfixed:]
    acc = np.zeros_like(Q)
    wsum = np.zeros(len(Q))
    for i in inputs_fields:
        P = pres[i]
        Fs = surfaces[i]
        if len(Fs) == 0:
            continue
        d2, fid, C = igl.point_mesh_squared_distance(Q, P.welded.V, Fs)
        T = Fs[fid]
        B = igl.barycentric_coordinates(C, P.welded.V[T[:, 0]], P.welded.V[T[:, 1]], P.welded.V[T[:, 2]])
        B = np.clip(np.nan_to_num(B, nan=1 / 3), 0, 1)
        p = np.einsum("nk,nk->n", B / np.maximum(B.sum(axis=1, keepdims=True), 1e-12), P.p_welded[T])
        w = p / (np.sqrt(d2) + h)
        acc += w[:, None] * C
        wsum += w
    ok = wsum > 0
    target = np.where(ok[:, None], acc / np.maximum(wsum, 1e-300)[:, None], Q)
    move = target - Q
    n = np.linalg.norm(move, axis=1)
    lim = max_voxels * h
    move *= np.minimum(1.0, lim / np.maximum(n, 1e-300))[:, None]
    out = U.copy()
    out[nfixed:] = Q + move
    return out


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


def _surface_input_vertices(pres, inputs_fields, junction_masks, grid, field3, h):
    """Vertices of the inputs' replaced faces that lie on the blended surface (``|f| < h/4``)."""
    from scipy.ndimage import map_coordinates

    pts = []
    for i in inputs_fields:
        P = pres[i]
        T = P.welded.F[junction_masks[i]]
        if len(T) == 0:
            continue
        v = np.unique(T.ravel())
        on_kept = np.zeros(len(P.welded.V), bool)
        on_kept[P.welded.F[~junction_masks[i]].ravel()] = True  # loop vertices stay where they are
        v = v[(P.p_welded[v] > 0) & ~on_kept[v]]
        X = P.welded.V[v]
        ijk = (X - grid.origin) / grid.voxel
        inside = np.all((ijk >= 0) & (ijk <= np.asarray(grid.shape) - 1), axis=1)
        X, ijk = X[inside], ijk[inside]
        if len(X) == 0:
            continue
        f = map_coordinates(field3, ijk.T, order=1, mode="nearest")
        pts.append(X[np.abs(f) < 0.25 * h])
    if not pts:
        return np.zeros((0, 3))
    X = np.unique(np.concatenate(pts), axis=0)
    # never onto a position a kept face of any input already has (it would weld into a seam)
    kept = [P.welded.V[np.unique(P.welded.F[~junction_masks[i]].ravel())] for i, P in enumerate(pres)]
    K = np.ascontiguousarray(np.concatenate(kept)) if kept else np.zeros((0, 3))
    key = np.dtype((np.void, 24))
    clash = np.isin(np.ascontiguousarray(X).view(key).ravel(), K.view(key).ravel())
    return X[~clash]


def _junction_for_cluster(grid, pres, surfaces, preserved, loops, inputs_fields, actions, params, band, timings,
                          local_edge=0.0, junction_masks=None):
    """Isosurface, cut, bridges and remesh of one cluster.

    Returns
    -------
    JV : (k, 3), JF : (q, 3), fixed_keys : list of (input, welded vertex) for ``JV[:len]``,
    info : dict
    """
    import igl

    t0 = time.perf_counter()
    field3 = _field_for_cluster(grid, inputs_fields, actions, band).reshape(grid.shape)
    timings["blend"] = timings.get("blend", 0.0) + time.perf_counter() - t0
    t0 = time.perf_counter()
    Vi, Fi = isosurface(field3, grid.origin, grid.voxel)
    timings["isosurface"] = timings.get("isosurface", 0.0) + time.perf_counter() - t0
    t0 = time.perf_counter()
    h = grid.voxel
    info = {"iso_faces": int(len(Fi)), "unmatched_preserved_loops": 0, "unmatched_iso_loops": 0,
            "orientation_warnings": 0}
    # cut: remove the isosurface where a preserved face is within cut_voxels
    if len(Vi):
        dmin = np.full(len(Vi), np.inf)
        for i, P in enumerate(pres):
            Fp = P.welded.F[preserved[i] & ~P.secondary]
            if len(Fp) == 0:
                continue
            d2, _, _ = igl.point_mesh_squared_distance(Vi, P.welded.V, Fp)
            dmin = np.minimum(dmin, np.sqrt(d2))
        Vc, Fc, _ = clip_mesh(Vi, Fi, dmin - params.cut_voxels * h)
        for _ in range(3):  # boundaries through one vertex twice: open them up
            bad = _pinched(Fc) if len(Fc) else np.zeros(0, bool)
            if not bad.any():
                break
            Vc, Fc, _ = remove_unreferenced(Vc, Fc[~bad])
    else:
        Vc, Fc = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    iso_loops, _ = boundary_loops(Vc, Fc, -1) if len(Fc) else ([], [])
    # match preserved loops to isosurface loops (or to each other across inputs)
    edge = np.mean([np.linalg.norm(np.diff(np.vstack([L.positions, L.positions[:1]]), axis=0), axis=1).mean()
                    for L in loops]) if loops else h
    max_cost = max(params.cut_voxels * h * 3.0 + 2.0 * h, 1.5 * edge)
    pairs = match_loops(loops, iso_loops, max_cost=max_cost)
    matched_iso = [j for i, kind, j in pairs if kind == "iso"]
    matched_pres = {i for i, _, _ in pairs} | {j for _, kind, j in pairs if kind == "preserved"}
    info["unmatched_preserved_loops"] = int(len(loops) - len(matched_pres))
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
            info["unmatched_iso_loops"] += 1
        if extra_v:
            Vc = np.concatenate([Vc, np.asarray(extra_v)])
            Fc = np.concatenate([Fc, np.asarray(extra_f, np.int64)])
    else:
        Vc, Fc = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
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
            info["orientation_warnings"] += 1
            log.warning("fusion: loops of different orientation bridged near %s", P.positions.mean(axis=0))
        T = bridge_loops(P.positions, Q.positions)
        pid = np.array([fixed_id(P.source, v, x) for v, x in zip(P.vertices, P.positions)]) + nI
        if kind == "iso":
            qid = Q.vertices
        else:
            qid = np.array([fixed_id(Q.source, v, x) for v, x in zip(Q.vertices, Q.positions)]) + nI
        ids = np.concatenate([pid, qid])
        faces.append(ids[T])
    fixed_pos = np.asarray(fixed_pos, dtype=np.float64).reshape(-1, 3)
    JV = np.concatenate([Vc, fixed_pos])
    JF = np.concatenate([Fc] + faces) if (len(Fc) or faces) else np.zeros((0, 3), np.int64)
    timings["cut_bridge"] = timings.get("cut_bridge", 0.0) + time.perf_counter() - t0
    t0 = time.perf_counter()
    fixed = np.arange(nI, nI + len(fixed_pos))
    # remesh the union with the preserved loops fixed (drop unused fixed vertices first)
    JV, JF, old = remove_unreferenced(JV, JF)
    isfixed = old >= nI
    fixed_keys = {v: k for k, v in keys.items()}
    if len(JF) and is_edge_manifold(JF):
        fx = np.flatnonzero(isfixed)
        # fine enough for the shape, never much finer than the fixed seam edges (slivers)
        target = params.target_edge_factor * min(edge, local_edge if local_edge > 0 else edge)
        target = max(target, 0.5 * edge)
        try:
            U, G = remesh_junction(JV, JF, fx, target=target, iterations=params.remesh_iterations)
            U = smooth_interior(U, G, np.arange(len(fx)), iterations=params.taubin_iterations)
            U = _project_to_inputs(U, len(fx), pres, surfaces, inputs_fields, h, params.project_voxels)
            fid_to_final = {int(old[v] - nI): k for k, v in enumerate(fx)}
            forb = _preserved_edges_between(pres, preserved, keys, fid_to_final)
            G = flip_to_improve_angles(U, G, forbidden=forb)
            U = relocate_poor_vertices(U, G, len(fx), surface=(JV, JF))
            G = flip_to_improve_angles(U, G, forbidden=forb)
            if params.snap_input_vertices and field3 is not None:
                targets = _surface_input_vertices(pres, inputs_fields, junction_masks, grid, field3, h)
                U = snap_to_points(U, G, len(fx), targets, max_dist=0.5 * target)
                G = flip_to_improve_angles(U, G, forbidden=forb)
            fkeys = [fixed_keys[int(old[v] - nI)] for v in fx]
            JV, JF = U, G
            info["remeshed"] = True
        except Exception as exc:  # remeshing is an improvement, never a reason to fail
            log.warning("fusion: junction remeshing failed (%s); keeping the bridged mesh", exc)
            info["remeshed"] = False
            fkeys = None
    else:
        info["remeshed"] = False
        fkeys = None
    if fkeys is None:
        order = np.concatenate([np.flatnonzero(isfixed), np.flatnonzero(~isfixed)])
        inv = np.empty_like(order)
        inv[order] = np.arange(len(order))
        JV, JF = JV[order], inv[JF]
        fkeys = [fixed_keys[int(old[v] - nI)] for v in np.flatnonzero(isfixed)]
    timings["remesh"] = timings.get("remesh", 0.0) + time.perf_counter() - t0
    return JV, JF, fkeys, info, field3


def fuse_surfaces(inputs: Sequence[FusionInput], actions: Sequence[FusionAction], *,
                  params: FusionParams = FusionParams()) -> FusedSurface:
    """Fuse the input surfaces into M_R = preserved parts + junction surface.

    Parameters
    ----------
    inputs : sequence of FusionInput
        Positioned rest-pose surfaces with their weights and kept joints.
    actions : sequence of FusionAction
        Which inputs meet and how (``replace``: presence-weighted blend of the signed distances;
        ``attach``: union). A junction no action covers (a removed subtree) is capped.
    params : FusionParams

    Returns
    -------
    FusedSurface
        Preserved faces copied bit-identically (positions, UVs, normals), junction faces
        appended, with the report described there.

    Raises
    ------
    InputError
        Malformed inputs or actions.
    """
    import igl

    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    inputs = list(inputs)
    actions = list(actions)
    _check_inputs(inputs, actions)
    t0 = time.perf_counter()
    pres = [compute_presence(x.V, x.F, x.W, x.used, snap=params.snap, iterations=params.smooth_iterations,
                             alpha=params.smooth_alpha, preserve_threshold=params.preserve_threshold,
                             morphology_rounds=params.morphology_rounds,
                             secondary_variance=params.secondary_variance) for x in inputs]
    edge_lengths = [average_edge_length(P.welded.V, P.welded.F) for P in pres]
    h0 = params.voxel_factor * min([e for e in edge_lengths if e > 0] or [1.0])
    preserved = _attach_conflicts(pres, actions, h0 * params.attach_conflict_voxels / 2.0)
    if params.min_seam_wedge > 0:
        preserved = [_open_notches(P, preserved[i], min_wedge=params.min_seam_wedge) for i, P in enumerate(pres)]
    junction = [~preserved[i] & ~(P.absent & ~P.preserved) for i, P in enumerate(pres)]
    if len(pres) > 1 and any(j.any() for j in junction):
        # the finest voxel any junction will get bounds the room the cut needs between seams
        boxes0 = _clusters(pres, junction, params.margin_voxels * h0)
        h_est = min(_grid_for(lo, hi, h0, params).voxel for lo, hi in boxes0)
        preserved = _separate_seams(pres, preserved, (2.0 * params.cut_voxels + 1.5) * h_est)
        preserved = _drop_specks(pres, preserved, params.min_island_faces)
        preserved = _unpinch_preserved(pres, preserved)
        if params.min_seam_wedge > 0:
            preserved = [_open_notches(P, preserved[i], min_wedge=params.min_seam_wedge) for i, P in enumerate(pres)]
        junction = [~preserved[i] & ~(P.absent & ~P.preserved) for i, P in enumerate(pres)]
    timings["presence"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    loops_all, open_chain_edges = [], 0
    for i, P in enumerate(pres):
        L, c = _preserved_loops(P, preserved[i], i)
        loops_all += L
        open_chain_edges += c
    boxes = _clusters(pres, junction, params.margin_voxels * h0)
    backend = get_backend(params.backend)
    # secondary components are kept whole or dropped, never blended: not in the fields
    surfaces = [prepare_surface(P.welded.V, P.welded.F[~P.secondary]) for P in pres]
    timings["setup"] = time.perf_counter() - t0

    juncs, grids_info, kept_fields, infos = [], [], [], []
    selected = [np.zeros(len(P.welded.F), bool) for P in pres]
    for ci, (lo, hi) in enumerate(boxes):
        grid = _grid_for(lo, hi, h0, params)
        band = params.band_voxels * grid.voxel
        t0 = time.perf_counter()
        fields = {}
        # inputs with the same geometry (a character composed with itself) share one field
        groups: dict = {}
        for i, P in enumerate(pres):
            Vw, Fs = P.welded.V, surfaces[i]
            P3 = Vw[Fs].reshape(-1, 3) if len(Fs) else np.zeros((0, 3))
            if len(P3) == 0 or np.any(P3.min(axis=0) > grid.upper + band) or np.any(P3.max(axis=0) < grid.origin - band):
                continue
            key = (Vw.shape, Fs.shape, hash(Vw.tobytes()), hash(Fs.tobytes()))
            groups.setdefault(key, []).append(i)
        for members in groups.values():
            P = pres[members[0]]
            vals = np.stack([pres[i].p_welded for i in members], axis=1)
            d, val = backend.signed_distance(grid, P.welded.V, surfaces[members[0]], vals, band=band)
            for c, i in enumerate(members):
                fields[i] = (d, val[:, c])
        timings["fields"] = timings.get("fields", 0.0) + time.perf_counter() - t0
        lo_g, hi_g = grid.origin, grid.upper
        cl = [L for L in loops_all
              if np.all(L.positions.mean(axis=0) >= lo_g) and np.all(L.positions.mean(axis=0) <= hi_g)]
        JV, JF, fkeys, info, field3 = _junction_for_cluster(grid, pres, surfaces, preserved, cl, fields, actions, params,
                                                            band, timings, _local_edge(pres, junction, grid),
                                                            junction_masks=junction)
        info.update(voxel_size=grid.voxel, voxels=grid.size, shape=list(grid.shape), loops=len(cl))
        if info["unmatched_preserved_loops"] > 0 or len(JF) == 0:
            # no closed junction (open sheets have no inside; loops left unmatched): keep the
            # input faces of the cluster from the input that is most present on each
            sel = _select_faces(pres, junction, grid)
            for i in range(len(pres)):
                selected[i] |= sel[i]
            info["fallback"] = "face-selection"
            log.warning("fusion: junction %d could not be closed by the isosurface (%d loops left); "
                        "kept the most present input faces instead", ci, info["unmatched_preserved_loops"])
            JV, JF, fkeys = np.zeros((0, 3)), np.zeros((0, 3), np.int64), []
        infos.append(info)
        juncs.append((JV, JF, fkeys))
        if params.keep_fields:
            kept_fields.append((f"junction_{ci}", grid, field3.astype(np.float32)))

    # assembly -----------------------------------------------------------------------------
    t0 = time.perf_counter()
    Vs, Fs_out, oin, over, foin, fof, mov = [], [], [], [], [], [], []
    uv_l, nrm_l, col_l = [], [], []
    has_uv = all(x.uvs is not None for x in inputs)
    has_n = all(x.normals is not None for x in inputs)
    has_c = any(x.colors is not None for x in inputs)
    base = 0
    nsel, sel_ranges = 0, []
    for i, x in enumerate(inputs):
        fidx = np.concatenate([np.flatnonzero(preserved[i]), np.flatnonzero(selected[i] & ~preserved[i])])
        nsel += int(np.count_nonzero(selected[i] & ~preserved[i]))
        sel_ranges.append((sum(len(f) for f in fof) + int(np.count_nonzero(preserved[i])), len(fidx) - int(np.count_nonzero(preserved[i]))))
        Fi = np.asarray(x.F, np.int64)[fidx]
        vidx = np.unique(Fi.ravel())
        remap = np.full(len(x.V), -1, np.int64)
        remap[vidx] = base + np.arange(len(vidx))
        Vs.append(np.asarray(x.V, np.float64)[vidx])
        Fs_out.append(remap[Fi])
        oin.append(np.full(len(vidx), i))
        over.append(vidx)
        foin.append(np.full(len(fidx), i))
        fof.append(fidx)
        mov.append(np.asarray(x.mesh_of_vertex)[vidx] if x.mesh_of_vertex is not None else np.zeros(len(vidx), np.int64))
        if has_uv:
            uv_l.append(np.asarray(x.uvs, np.float64)[vidx])
        if has_n:
            nrm_l.append(np.asarray(x.normals, np.float64)[vidx])
        if has_c:
            col_l.append(np.asarray(x.colors, np.float64)[vidx] if x.colors is not None else np.ones((len(vidx), 4)))
        base += len(vidx)
    n_pres_faces = sum(len(f) for f in Fs_out)
    jstart = base
    for JV, JF, _ in juncs:
        Vs.append(JV)
        Fs_out.append(JF + base)
        base += len(JV)
    nJ = base - jstart
    V_out = np.concatenate(Vs) if Vs else np.zeros((0, 3))
    F_out = np.concatenate(Fs_out).astype(np.int64) if Fs_out else np.zeros((0, 3), np.int64)
    junction_faces = np.zeros(len(F_out), bool)
    junction_faces[n_pres_faces:] = True
    for start, count in sel_ranges:
        junction_faces[start:start + count] = True
    JVall = V_out[jstart:]
    JFall = F_out[n_pres_faces:] - jstart

    # junction attributes: closest points on each input, presence-weighted colours
    sources = []
    wsum = np.zeros(nJ)
    csum = np.zeros((nJ, 4))
    for i, x in enumerate(inputs):
        if nJ == 0:
            sources.append({"face": np.zeros(0, np.int64), "bary": np.zeros((0, 3)), "distance": np.zeros(0),
                            "presence": np.zeros(0)})
            continue
        Vx = np.asarray(x.V, np.float64)
        Fx = np.asarray(x.F, np.int64)
        d2, fid, C = igl.point_mesh_squared_distance(JVall, Vx, Fx)
        T = Fx[fid]
        B = igl.barycentric_coordinates(C, Vx[T[:, 0]], Vx[T[:, 1]], Vx[T[:, 2]])
        B = np.clip(np.nan_to_num(B, nan=1 / 3), 0, 1)
        B /= np.maximum(B.sum(axis=1, keepdims=True), 1e-12)
        p = np.einsum("nk,nk->n", B, pres[i].p[T])
        sources.append({"face": fid, "bary": B, "distance": np.sqrt(d2), "presence": p})
        if has_c:
            cx = np.asarray(x.colors, np.float64) if x.colors is not None else np.ones((len(Vx), 4))
            w = p / (np.sqrt(d2) + 1e-3 * h0)
            csum += w[:, None] * np.einsum("nk,nkc->nc", B, cx[T])
            wsum += w
    uvs = normals = colors = None
    if has_uv:
        uvs = np.concatenate(uv_l + [np.zeros((nJ, 2))])
    if has_n:
        jn = igl.per_vertex_normals(JVall, JFall) if len(JFall) else np.zeros((nJ, 3))
        normals = np.concatenate(nrm_l + [np.nan_to_num(np.asarray(jn))])
    if has_c:
        jc = csum / np.maximum(wsum, 1e-12)[:, None]
        jc[wsum <= 0] = 1.0
        colors = np.concatenate(col_l + [jc])
    origin_input = np.concatenate(oin + [np.full(nJ, -1)]).astype(np.int64)
    origin_vertex = np.concatenate(over + [np.full(nJ, -1)]).astype(np.int64)
    timings["assembly"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    mrep = mesh_report(V_out, F_out, junction_faces, [(x.V, x.F) for x in inputs])
    mrep["unmatched_loops"] = int(sum(inf["unmatched_preserved_loops"] for inf in infos))
    mrep["open_seam_edges"] = int(open_chain_edges)
    timings["report"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    report = {
        "mesh": mrep,
        "fields": {
            "voxel_size": float(min([g["voxel_size"] for g in infos], default=h0)),
            "voxels": int(sum(g["voxels"] for g in infos)),
            "backend": backend.name,
            "grids": infos,
        },
        "timings": {k: round(v, 4) for k, v in timings.items()},
    }
    return FusedSurface(
        V=V_out, F=F_out, origin_input=origin_input, origin_vertex=origin_vertex,
        face_origin_input=np.concatenate(foin + [np.full(len(F_out) - n_pres_faces, -1)]).astype(np.int64),
        face_origin_face=np.concatenate(fof + [np.full(len(F_out) - n_pres_faces, -1)]).astype(np.int64),
        junction_faces=junction_faces, preserved=tuple(preserved), presence=tuple(P.p for P in pres),
        mesh_of_vertex=np.concatenate(mov + [np.full(nJ, -1)]).astype(np.int64),
        uvs=uvs, normals=normals, colors=colors, junction_sources=tuple(sources),
        fields=tuple(kept_fields), report=report,
    )
