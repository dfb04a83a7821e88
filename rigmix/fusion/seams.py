"""Preserved parts and junction regions: which faces are kept and where the junctions lie.

Helpers of :func:`rigmix.fusion.fuse_surfaces` (PIPELINE.md section 3): attach and burial
conflicts, seam separation, specks and pinches, thin wedges, junction clusters and their grids,
seam loops, and the face-selection fallback.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..geometry import check_grid_voxels
from .fields import Grid
from .junction import boundary_loops
from .meshutil import (
    boundary_halfedges,
    corner_angles,
    edge_counts,
    face_adjacency,
    nondegenerate,
    undirected_edges,
)
from .presence import Presence, kept_shells

__all__ = [
    "attach_conflicts",
    "pinched_faces",
    "unpinch_preserved",
    "closed_past_junction",
    "drop_specks",
    "separate_seams",
    "open_notches",
    "under_kept_shells",
    "junction_clusters",
    "cluster_grid",
    "preserved_loops",
    "most_present_faces",
    "local_edge_length",
    "coincident_faces",
    "shared_preserved",
]


def attach_conflicts(pres: list[Presence], actions, h, surfaces):
    """Preserved faces the fused surface must cut through or that it buries.

    attach: faces of either input near or inside the other's present part. replace: faces of
    one input buried inside the present part of the other (the rider's hips inside the horse):
    their seams would have no isosurface to meet. Faces on the other surface itself (a
    character composed with itself) are not buried.

    Parameters
    ----------
    pres : list of Presence
        One per input.
    actions : sequence of FusionAction
    h : float
        Distance unit (same units as the meshes): attach conflicts lie within ``2 h`` of the
        other's present part, buried faces farther than ``h / 2`` from the other's surface.
    surfaces : list of (g_i, 3) int arrays
        Per input, its non-secondary welded faces prepared by :func:`.fields.prepare_surface`
        (the same the fusion's fields use).

    Returns
    -------
    list of (m_i,) bool arrays
        Per input, its preserved welded faces without the conflicting ones.
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
            if act.kind == "attach":
                d2, _, _ = igl.point_mesh_squared_distance(C, Vy, Fy)
                w = igl.fast_winding_number(Vy, Fy, C)
                hit = (d2 < (h * 2.0) ** 2) | (np.abs(w) > 0.5)
            else:
                # inside the other's whole surface, nearest to a present part of it, not on it; the
                # distances only for the centres inside (each query is answered on its own)
                Fall = surfaces[y]
                hit = igl.fast_winding_number(Vy, Fall, C) > 0.5
                inside = np.flatnonzero(hit)
                if len(inside):
                    d2a, fa, _ = igl.point_mesh_squared_distance(C[inside], Vy, Fall)
                    pa = Py.p_welded[Fall[fa]].mean(axis=1)
                    hit[inside] = (pa >= 0.5) & (d2a > (0.5 * h) ** 2)
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


def pinched_faces(F):
    """Faces at a vertex where the mesh's boundary passes more than once.

    Boundary edges are counted without their direction: where the faces' orientation flips
    along a line that meets the boundary (the Witch's collar), one pass of the boundary through
    a vertex has two outgoing half-edges, and counting those took it for two passes.

    Parameters
    ----------
    F : (m, 3) int array

    Returns
    -------
    (m,) bool array
        Faces with a corner on more than two boundary edges.
    """
    B = boundary_halfedges(F)
    if len(B) == 0:
        return np.zeros(len(F), bool)
    n = int(np.max(F)) + 1
    cnt = np.bincount(B.ravel(), minlength=n)
    return (cnt[F] > 2).any(axis=1)


def unpinch_preserved(pres: list[Presence], preserved, rounds=8):
    """Un-preserve the faces at seam vertices the preserved boundary visits twice, and those on
    a non-manifold edge past which the junction continues (:func:`closed_past_junction`).

    Two seam loops through one vertex would both be bridged from it and give an edge of three
    or four faces; a seam cannot run along an edge that two preserved faces close.

    Parameters
    ----------
    pres : list of Presence
    preserved : list of (m_i,) bool arrays
        Per input, preserved welded faces.
    rounds : int
        Passes at most (un-preserving faces can pinch the boundary elsewhere, or bring the
        junction to another non-manifold edge: the Frog's legs, standing on her body along
        such edges, take 4 or 5).

    Returns
    -------
    list of (m_i,) bool arrays
        New masks; the inputs are not modified.
    """
    out = [m.copy() for m in preserved]
    for i, P in enumerate(pres):
        for _ in range(rounds):
            idx = np.flatnonzero(out[i])
            if len(idx) == 0:
                break
            bad = pinched_faces(P.welded.F[idx])
            replaced = ~out[i] & ~P.absent & ~P.secondary
            bad |= closed_past_junction(P.welded.F, out[i], replaced)[idx]
            if not bad.any():
                break
            out[i][idx[bad]] = False
    return out


def closed_past_junction(F, preserved, replaced):
    """Preserved faces on a non-manifold edge that two preserved faces close and a replaced face
    also uses, where a seam ends.

    Such an edge is no boundary of the preserved faces, so no seam runs along it, yet the
    junction face hanging from it is replaced: a seam that reaches it stops there, an open chain
    (the Frog's legs stand on her body along non-manifold edges). Only while some seam ends
    (a vertex on an odd number of seam edges): where every seam closes, such edges are left
    alone, the junction meeting the seams elsewhere (opening them all up there leaves small
    seam loops that no isosurface hole matches: the Frog's right hind leg mirrored).

    Parameters
    ----------
    F : (m, 3) int array
        Welded faces of one input.
    preserved, replaced : (m,) bool arrays

    Returns
    -------
    (m,) bool array
        Preserved faces on such edges; none where no seam ends.
    """
    ok = nondegenerate(F)
    idx = np.flatnonzero(ok)
    _, uE, emap = undirected_edges(F[idx])
    face = np.tile(idx, 3)
    count = np.bincount(emap, minlength=len(uE))
    kept = np.bincount(emap, weights=preserved[face], minlength=len(uE))
    gone = np.bincount(emap, weights=replaced[face], minlength=len(uE))
    seam = (kept == 1) & (count >= 2)  # as in preserved_loops
    ends = np.bincount(uE[seam].ravel(), minlength=len(F) and int(F.max()) + 1) % 2 == 1
    if not ends.any():
        return np.zeros(len(F), bool)
    bad_edge = (kept >= 2) & (gone >= 1)
    out = np.zeros(len(F), bool)
    out[face[bad_edge[emap] & preserved[face]]] = True
    return out


def drop_specks(pres: list[Presence], preserved, min_faces):
    """Un-preserve preserved parts bordering a junction with fewer than ``min_faces`` faces
    (and under 2% of the input's faces: a low-poly limb of a dozen faces is no speck).

    Parameters
    ----------
    pres : list of Presence
    preserved : list of (m_i,) bool arrays
        Per input, preserved welded faces.
    min_faces : int

    Returns
    -------
    list of (m_i,) bool arrays
        New masks; the inputs are not modified.
    """
    out = [m.copy() for m in preserved]
    for i, P in enumerate(pres):
        limit = min(min_faces, 0.02 * len(P.welded.F))
        for f in _seam_components(P, preserved[i]):
            if len(f) < limit:
                out[i][f] = False
    return out


def separate_seams(pres: list[Presence], preserved, delta):
    """Un-preserve faces closer than ``delta`` to another preserved part bordering a junction.

    Where two preserved parts (of two inputs, or two parts of one input on either side of a
    junction) come closer than the isosurface cut leaves room for (the underside of a limb
    against the body), the cut isosurface would pinch there and its boundary loops merge,
    which no loop-to-loop bridge can close; widening the junction keeps every seam its own loop.

    Parameters
    ----------
    pres : list of Presence
    preserved : list of (m_i,) bool arrays
        Per input, preserved welded faces.
    delta : float
        Distance (same units as the meshes).

    Returns
    -------
    list of (m_i,) bool arrays
        New masks; the inputs are not modified.
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


def open_notches(P: Presence, preserved, *, min_wedge=60.0, rounds=3):
    """Un-preserve the faces around seam vertices where the junction would be a thin wedge.

    At a vertex of the preserved boundary, the junction gets what the preserved faces leave of
    the angle around it; below ``min_wedge`` degrees no triangulation reaches a good minimum
    angle there, so the preserved faces at that vertex join the junction.

    Parameters
    ----------
    P : Presence
        One input.
    preserved : (m,) bool array
        Its preserved welded faces.
    min_wedge : float
        Degrees.
    rounds : int
        Passes (opening a notch can leave a thin wedge beside it).

    Returns
    -------
    (m,) bool array
        New mask; ``preserved`` is not modified.
    """
    Fw = P.welded.F
    ok = ~P.absent | preserved
    ang = np.degrees(corner_angles(P.welded.V, Fw))
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


def under_kept_shells(pres: list[Presence], preserved, junction, *, rounds=64):
    """Un-preserve the faces, next to a junction, that a kept closed part covers.

    A modular character's rigid part (a leg plugged into the thorax, an arm's shoulder cylinder)
    is kept whole and is not in the fields. Where it lands on another input's preserved surface,
    that surface runs on inside it up to the seam, and every junction face the seam starts
    crosses the part: no move of the junction's own vertices can take them out. The covered faces
    join the junction instead, so that the junction starts outside the part and can go around
    it (``FusionParams.shell_clearance_voxels``). Another input's part takes every face it
    reaches into; an input's own part, laid over its surface by its artist, only the faces it
    hides whole. Only faces joined to a junction through covered
    faces are taken: a covered patch away from every junction stays as it is (the part hides
    it), no new hole opens, and an input whose seam would split into more pieces keeps its faces.

    Parameters
    ----------
    pres : list of Presence
    preserved, junction : list of (m_i,) bool arrays
        Per input, preserved and junction welded faces.
    rounds : int
        Rings of covered faces taken from a junction at most.

    Returns
    -------
    list of (m_i,) bool arrays
        New preserved masks; the inputs are not modified.
    """
    out = [m.copy() for m in preserved]
    shells = [kept_shells(P, preserved[j]) for j, P in enumerate(pres)]
    for i, P in enumerate(pres):
        V, F = P.welded.V, P.welded.F
        if not junction[i].any():
            continue
        by_other, by_own = np.zeros(len(V), bool), np.zeros(len(V), bool)
        for j, Q in enumerate(pres):
            if len(shells[j]):
                covered = by_own if j == i else by_other
                covered |= _inside_closed(Q.welded.V, shells[j], V)
        in_shell = np.zeros(len(V), bool)
        in_shell[shells[i].ravel()] = True  # a part does not cover itself
        # another character's part: every face it reaches into; the input's own parts, which
        # its artist laid over its surface: only the faces they hide whole
        take = out[i] & ~in_shell[F].all(axis=1) & (by_other[F].any(axis=1) | by_own[F].all(axis=1))
        if not take.any():
            continue
        reach = np.zeros(len(V), bool)
        reach[F[junction[i]].ravel()] = True
        grown = np.zeros(len(F), bool)
        for _ in range(rounds):
            new = take & ~grown & reach[F].any(axis=1)
            if not new.any():
                break
            grown |= new
            reach[F[new].ravel()] = True
        # a seam that splits in two (a preserved island cut off) is a loop no bridge expects
        if _border_count(F, out[i] & ~grown & ~P.secondary) <= _border_count(F, out[i] & ~P.secondary):
            out[i] &= ~grown
    return out


def _inside_closed(Vs, Fs, X):
    """``(len(X),) bool``: points ``X`` inside the closed surface ``Fs`` over ``Vs`` (winding
    number above 1/2); only those within its bounding box are tested."""
    import igl

    out = np.zeros(len(X), bool)
    T = Vs[Fs].reshape(-1, 3)
    near = np.flatnonzero(np.all((X >= T.min(axis=0)) & (X <= T.max(axis=0)), axis=1))
    if len(near):
        w = igl.fast_winding_number(np.ascontiguousarray(Vs, np.float64), np.ascontiguousarray(Fs, np.int64),
                                    np.ascontiguousarray(X[near], np.float64))
        out[near[w > 0.5]] = True
    return out


def _border_count(F, faces):
    """Connected pieces of the border of the faces ``faces`` ``(m,) bool`` of ``F`` (their
    boundary edges joined at shared vertices): the seam loops and open borders they make."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    B = boundary_halfedges(F[faces])
    if not len(B):
        return 0
    verts, inv = np.unique(B.ravel(), return_inverse=True)
    inv = inv.reshape(-1, 2)
    A = coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(len(verts), len(verts)))
    return int(connected_components(A, directed=False)[0])


def junction_clusters(pres, junction, margin):
    """Boxes around the face-connected parts of the junction, boxes within ``2 margin`` merged.

    Parameters
    ----------
    pres : list of Presence
    junction : list of (m_i,) bool arrays
        Per input, the welded faces the junction replaces.
    margin : float
        Same units as the meshes.

    Returns
    -------
    list of [lo, hi]
        Corners ``(3,)`` of each box (without the margin), one per junction cluster.
    """
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


def cluster_grid(lo, hi, h0, params, diagonal=0.0):
    """The grid of one junction box: voxel ``h0``, refined so that ``min_voxels_across`` span
    the box's second largest extent and one voxel is at most ``max_voxel_diagonal`` of the
    smallest input's bounding-box diagonal, then coarsened to respect ``max_voxels``.

    Parameters
    ----------
    lo, hi : (3,) float arrays
        The box (:func:`junction_clusters`).
    h0 : float
        Coarsest voxel (same units as the meshes).
    params : FusionParams
        ``min_voxels_across``, ``max_voxel_diagonal``, ``margin_voxels``, ``cut_voxels`` and
        ``max_voxels`` are read.
    diagonal : float
        Smallest input's bounding-box diagonal (0: no diagonal rule).

    Returns
    -------
    Grid
        Reaching ``max(margin_voxels, cut_voxels + 4)`` voxels beyond the box.
    """
    ext = hi - lo
    across = np.sort(ext)[1]
    h = min(h0, across / max(params.min_voxels_across, 1)) if across > 0 else h0
    if diagonal > 0 and params.max_voxel_diagonal > 0:
        h = min(h, params.max_voxel_diagonal * diagonal)
    for _ in range(20):
        margin = max(params.margin_voxels * h, (params.cut_voxels + 4) * h)
        glo = lo - margin
        shape = tuple(int(x) for x in np.ceil((hi + margin - glo) / h) + 1)
        if np.prod(shape) <= params.max_voxels:
            break
        h *= (np.prod(shape) / params.max_voxels) ** (1 / 3) * 1.02
    check_grid_voxels(shape, where="fusion", limit=params.max_voxels)
    return Grid(glo, float(h), shape)


def _halfedge_keys(V, H):
    """Keys of directed half-edges ``H`` (k, 2) by their endpoint positions (bit-exact, start
    then end): ``(k,)`` numpy void array."""
    V = np.asarray(V, np.float64)
    K = np.ascontiguousarray(np.concatenate([V[H[:, 0]], V[H[:, 1]]], axis=1))
    return K.view(np.dtype((np.void, K.dtype.itemsize * 6))).ravel()


def preserved_loops(P: Presence, preserved, source, others=()):
    """Closed boundary loops of the preserved faces that run through the input's interior.

    A boundary edge where a kept face of another input continues the surface (the same two
    corner positions, bit for bit, in the opposite direction) is no seam: the output is closed
    there. That is where a shared face is kept from the other input
    (:func:`shared_preserved`, :func:`coincident_faces`).

    Parameters
    ----------
    P : Presence
        One input.
    preserved : (m,) bool array
        Its preserved (or copied) welded faces.
    source : int
        Input index recorded in each loop.
    others : sequence of (V, F)
        The other inputs' kept faces: positions ``(n_j, 3)`` and faces ``(f_j, 3)``.

    Returns
    -------
    loops : list of Loop
        Seam loops, over welded vertices of the input.
    open_edges : int
        Seam edges on chains that do not close (left unbridged).
    """
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
    covering = [np.asarray(F, np.int64).reshape(-1, 3) for _, F in others]
    if any(len(F) for F in covering):
        # the other inputs' half-edges reversed: one of them equal to ours continues the surface
        rev = np.concatenate([_halfedge_keys(V, np.concatenate([F[:, [1, 0]], F[:, [2, 1]], F[:, [0, 2]]]))
                              for (V, _), F in zip(others, covering)])
        interior &= ~np.isin(_halfedge_keys(P.welded.V, B), rev)
    loops, chains = boundary_loops(P.welded.V, None, source, halfedges=B[interior])
    if chains and not interior.all():
        closed, chains = _close_along_holes(P.welded.V, B, interior, chains, source)
        loops += closed
    return loops, int(sum(len(c) - 1 for c in chains))


def _close_along_holes(V, B, seam, chains, source):
    """Seam chains closed along the input's open border where they end on a small hole.

    The kept faces' boundary half-edges ``B`` ``(b, 2)`` chain into closed loops; where the seam
    (``seam``, ``(b,) bool``) runs into a hole of the input's mesh (a gap left at a tail's root),
    a loop is part seam, part hole border, and the seam alone is a chain the junction cannot
    bridge. Such a loop is taken whole when its border part is no longer than its seam part: the
    junction then closes the hole where it meets the seam. Longer borders (an open sleeve) stay
    open, and their chains with them.

    Returns
    -------
    loops : list of Loop
        The closed loops (seam and border edges).
    chains : list of (k,) int64 arrays
        The chains left open.
    """
    full, _ = boundary_loops(V, None, source, halfedges=B)

    def key(E):  # an undirected edge as one integer
        return np.minimum(E[:, 0], E[:, 1]) * (len(V) + 1) + np.maximum(E[:, 0], E[:, 1])

    seam_keys = key(B[seam])
    chain_keys = [key(np.stack([c[:-1], c[1:]], axis=1)) for c in chains]
    closed, used = [], set()
    for L in full:
        E = np.stack([L.vertices, np.roll(L.vertices, -1)], axis=1)
        on_seam = np.isin(key(E), seam_keys)
        if on_seam.all() or not on_seam.any():
            continue
        length = np.linalg.norm(V[E[:, 1]] - V[E[:, 0]], axis=1)
        if length[~on_seam].sum() > length[on_seam].sum():
            continue
        loop_keys = key(E)
        mine = [i for i, k in enumerate(chain_keys) if np.isin(k, loop_keys).all()]
        covered = np.concatenate([chain_keys[i] for i in mine]) if mine else []
        if not np.isin(loop_keys[on_seam], covered).all():  # its seam is not all on chains of its own
            continue
        closed.append(replace(L, hole_edges=int(np.count_nonzero(~on_seam))))
        used.update(mine)
    return closed, [c for i, c in enumerate(chains) if i not in used]


def most_present_faces(pres, junction, grid):
    """Fallback junction: each input's junction faces in ``grid`` where it is the most present.

    A face is kept from input ``i`` when its mean presence is above 0.5 (exactly 0.5: only for
    the first input), so a character composed with itself gets each face exactly once.

    Parameters
    ----------
    pres : list of Presence
    junction : list of (m_i,) bool arrays
        Per input, the welded faces the junction replaces.
    grid : Grid
        The cluster's grid; a face is in it when its centroid is.

    Returns
    -------
    list of (m_i,) bool arrays
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


def local_edge_length(pres, junction, grid):
    """Mean edge length of the input faces replaced by the junction inside ``grid``.

    Parameters
    ----------
    pres : list of Presence
    junction : list of (m_i,) bool arrays
        Per input, the welded faces the junction replaces.
    grid : Grid
        A face is in it when its centroid is.

    Returns
    -------
    float
        Same units as the meshes; 0 without such faces.
    """
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


def _face_pairs(Va, Fa, Vb, Fb):
    """Faces of mesh a and mesh b with the same corners (bit for bit: anything else would leave
    a crack where the copies of the two meshes meet) in the same cyclic order: ``(ia, ib)``
    int64 arrays of face indices, each face in at most one pair."""
    if len(Fa) == 0 or len(Fb) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    Vb = np.asarray(Vb, np.float64)
    _, inv = np.unique(np.concatenate([Vb, np.asarray(Va, np.float64)]), axis=0, return_inverse=True)
    inv = inv.ravel()
    first_b = np.full(inv.max() + 1, -1, np.int64)
    first_b[inv[:len(Vb)][::-1]] = np.arange(len(Vb))[::-1]
    to_b = first_b[inv[len(Vb):]]
    Fab = to_b[Fa]
    ok = np.flatnonzero((Fab >= 0).all(axis=1) & (Fab[:, 0] != Fab[:, 1]) & (Fab[:, 1] != Fab[:, 2])
                        & (Fab[:, 0] != Fab[:, 2]))

    def canonical(F):  # rotate each face so its smallest index comes first (orientation kept)
        r = np.argmin(F, axis=1)
        return np.stack([F[np.arange(len(F)), (r + k) % 3] for k in range(3)], axis=1)

    ka, kb = canonical(Fab[ok]), canonical(np.asarray(Fb, np.int64))
    rows, inv = np.unique(np.concatenate([kb, ka]), axis=0, return_inverse=True)
    inv = inv.ravel()
    first_b = np.full(len(rows), -1, np.int64)
    first_b[inv[:len(kb)][::-1]] = np.arange(len(kb))[::-1]
    ib = first_b[inv[len(kb):]]
    hit = ib >= 0
    ia, ib = ok[hit], ib[hit]
    _, u = np.unique(ib, return_index=True)  # duplicate faces of a: one pair per face of b
    return ia[u], ib[u]


def shared_preserved(pres: list[Presence], preserved, actions):
    """Preserved faces that another input of an action preserves too, each kept from one input.

    The joint an action fuses belongs to both inputs' kept joints, so the faces skinned to it
    alone (the upper arm of a limb replaced by itself, a shoulder pad or a robot's rigid part on
    that joint, a whole secondary component) have presence 1 in both. Where the two inputs have
    such a face with the same corners bit for bit in the same orientation, both copies would
    give the output every face twice and every edge around them three or four faces; one copy
    is kept, from the input more present on it (the action's first input, ``a``, on a tie).
    Faces that merely overlap (two different characters' upper arms) are left to the union.

    Parameters
    ----------
    pres : list of Presence
    preserved : list of (m_i,) bool arrays
        Per input, preserved welded faces.
    actions : sequence of FusionAction

    Returns
    -------
    list of (m_i,) bool arrays
        New masks, each shared face in one of them; the inputs are not modified.
    """
    out = [m.copy() for m in preserved]
    for act in actions:
        a, b = act.a, act.b
        Pa, Pb = pres[a], pres[b]
        ia, ib = _face_pairs(Pa.welded.V, Pa.welded.F, Pb.welded.V, Pb.welded.F)
        both = out[a][ia] & out[b][ib]
        pa = Pa.p_welded[Pa.welded.F[ia]].mean(axis=1)
        pb = Pb.p_welded[Pb.welded.F[ib]].mean(axis=1)
        keep_a = pa >= pb
        out[b][ib[both & keep_a]] = False
        out[a][ia[both & ~keep_a]] = False
    return out


def coincident_faces(pres: list[Presence], preserved, junction, actions, margin):
    """Junctions whose faces two inputs of an action share: both surfaces pass through every
    face, so the blend of their signed distances (or their union) vanishes there and the
    junction is those faces as they are.

    A shared face that one input preserves is dropped from the other's junction. A face in both
    junctions (or in one, absent from the other) is copied from the input more present on it
    (the first on a tie) and dropped from the other. This is done only for junction clusters
    (:func:`junction_clusters` with ``margin``) whose every face is shared: a partly shared junction
    would need seam loops that run along both inputs, and is remeshed from the fields instead.
    A character composed with itself thus gets every face back as it was (a limb replaced by
    itself); two different characters rarely share a face.

    Parameters
    ----------
    pres : list of Presence
    preserved, junction : lists of (m_i,) bool arrays
        Per input, preserved welded faces and the welded faces the junction replaces.
    actions : sequence of FusionAction
    margin : float
        Cluster margin (same units as the meshes), as in :func:`junction_clusters`.

    Returns
    -------
    copied, dropped : lists of (m_i,) bool arrays
        Per input, faces copied unchanged into the junction, and faces that leave the junction.
    """
    copied = [np.zeros(len(P.welded.F), bool) for P in pres]
    dropped = [np.zeros(len(P.welded.F), bool) for P in pres]
    for act in actions:
        a, b = act.a, act.b
        Pa, Pb = pres[a], pres[b]
        ia, ib = _face_pairs(Pa.welded.V, Pa.welded.F, Pb.welded.V, Pb.welded.F)
        live_a = junction[a][ia] & ~copied[a][ia] & ~dropped[a][ia]
        live_b = junction[b][ib] & ~copied[b][ib] & ~dropped[b][ib]
        # one side preserves it: the other's copy leaves the junction
        dropped[a][ia[live_a & preserved[b][ib]]] = True
        dropped[b][ib[live_b & preserved[a][ia]]] = True
        pa = Pa.p_welded[Pa.welded.F[ia]].mean(axis=1)
        pb = Pb.p_welded[Pb.welded.F[ib]].mean(axis=1)
        open_a = live_a & ~preserved[b][ib] & (~live_b | (pa >= pb))
        open_b = live_b & ~preserved[a][ia] & ~open_a
        copied[a][ia[open_a]] = True
        dropped[b][ib[open_a & live_b]] = True
        copied[b][ib[open_b]] = True
        dropped[a][ia[open_b & live_a]] = True
    for lo, hi in junction_clusters(pres, junction, margin):
        inside = []
        for i, P in enumerate(pres):
            c = P.welded.V[P.welded.F].mean(axis=1)
            inside.append(junction[i] & np.all((c >= lo - margin) & (c <= hi + margin), axis=1))
        if any(np.any(inside[i] & ~copied[i] & ~dropped[i]) for i in range(len(pres))):
            for i in range(len(pres)):
                copied[i] &= ~inside[i]
                dropped[i] &= ~inside[i]
    return copied, dropped
