"""One junction: blended field, isosurface, cut, bridges, remesh (PIPELINE.md section 3).

Helper of :func:`rigmix.fusion.fuse_surfaces`.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .fields import blend_attach, blend_cap, blend_replace, signed_distance_at
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
from .remesh import (
    collapse_to_improve_angles,
    flip_to_improve_angles,
    insert_points,
    is_edge_manifold,
    relocate_poor_vertices,
    remesh_junction,
    smooth_interior,
    snap_to_points,
    untangle,
)
from .meshutil import intersecting_face_pairs, triangle_min_angles
from .seams import _pinched

log = logging.getLogger(__name__)


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


def _surface_input_vertices(X, grid, field3, h):
    """The points of ``X`` where the sampled blended field is within a quarter voxel of 0."""
    from scipy.ndimage import map_coordinates

    if len(X) == 0:
        return X
    ijk = (X - grid.origin) / grid.voxel
    f = map_coordinates(field3, ijk.T, order=1, mode="nearest")
    return X[np.abs(f) < 0.25 * h]


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

    order = np.argsort(-np.asarray(priority))
    tree = cKDTree(avoid) if avoid is not None and len(avoid) else None
    pick: list[int] = []
    for k in order:
        if tree is not None and tree.query(X[k])[0] < (spacing if avoid_spacing is None else avoid_spacing):
            continue
        if pick and np.min(np.linalg.norm(X[pick] - X[k], axis=1)) < spacing:
            continue
        pick.append(int(k))
    return np.asarray(pick, np.int64)


def _angle_p05(V, F):
    """5th percentile of the triangles' minimum angles, degrees (0 without triangles)."""
    return float(np.percentile(triangle_min_angles(V, F), 5)) if len(F) else 0.0


def _remesh_keeping_features(V, F, fixed, target, iterations, tol, rounds, points=None, points_tol=None,
                             max_insert=None):
    """Remesh with ``fixed`` kept, then again keeping what the result lost.

    Remeshing to the neighbouring edge length chords off the corners and thin parts of the
    surface it follows. After each pass, the vertices of the reference ``(V, F)`` and the
    ``points`` (exact surface points: input corners) farther than ``tol`` from the result,
    farthest first, at least half a target edge apart and a quarter from the kept vertices,
    become fixed vertices of the next pass (points are inserted into the reference first): the
    remesher then builds its isotropic triangles around them. Before the first pass, the
    points the reference itself misses by more than ``points_tol`` (default ``tol``) and that
    lie within ``max_insert`` of it are inserted. At most ``rounds`` more passes.

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
    keep = fixed
    points = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64).reshape(-1, 3)

    def add_points(V, F, keep, X, dX):
        X = X[_spread(X, dX, 0.5 * target, avoid=V[keep], avoid_spacing=0.15 * target)]
        if len(X) == 0:
            return V, F, keep
        V, F, placed = insert_points(V, F, np.isin(np.arange(len(V)), fixed), X,
                                     max_dist=4.0 * tol if max_insert is None else max_insert)
        return V, F, np.concatenate([keep, placed[~np.isin(placed, keep)]])

    if tol > 0 and len(points):
        dX = np.sqrt(igl.point_mesh_squared_distance(points, V, F)[0])
        lost = dX > (tol if points_tol is None else points_tol)
        V, F, keep = add_points(V, F, keep, points[lost], dX[lost])
    U, G = remesh_junction(V, F, keep, target=target, iterations=iterations)
    for _ in range(rounds if tol > 0 else 0):
        d = np.sqrt(igl.point_mesh_squared_distance(V, U, G)[0])
        far = np.flatnonzero(d > tol)
        far = far[~np.isin(far, keep)]
        pick = far[_spread(V[far], d[far], 0.5 * target, avoid=V[keep], avoid_spacing=0.25 * target)]
        n_before = len(keep)
        keep = np.concatenate([keep, np.asarray(pick, np.int64)])
        if len(points):
            dX = np.sqrt(igl.point_mesh_squared_distance(points, U, G)[0])
            V, F, keep = add_points(V, F, keep, points[dX > tol], dX[dX > tol])
        if len(keep) == n_before:
            break
        U, G = remesh_junction(V, F, keep, target=target, iterations=iterations)
    return U, G, len(keep), (V, F)


def _junction_for_cluster(grid, pres, surfaces, preserved, loops, inputs_fields, actions, params, band, timings,
                          local_edge=0.0, junction_masks=None, diagonal=0.0):
    """Isosurface, cut, bridges and remesh of one cluster.

    Returns
    -------
    JV : (k, 3), JF : (q, 3), fixed_keys : list of (input, welded vertex) for ``JV[:len]``,
    info : dict
    """
    import igl

    t0 = time.perf_counter()
    field3 = _field_for_cluster(grid.size, inputs_fields, actions, band).reshape(grid.shape)
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

    def bridged(Vc, Fc):
        """Loops of the cut isosurface matched to the preserved loops and bridged: the junction
        before remeshing, its vertex table, the number of bridge faces (last in JF) and the
        mean seam edge."""
        info["unmatched_iso_loops"] = info["orientation_warnings"] = 0
        fans = {}  # fan centre vertex -> the positions of the hole's loop
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
                fans[c] = L.positions
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
        return JV, JF, nI, keys, len(JF) - len(Fc), edge, fans

    # a bridge strip must not pass through the isosurface, nor through the fan closing a hole no
    # seam claims (where the cut loop recedes far from its seam, or a second hole opens beside
    # it): the isosurface around what it crosses is cut away too and the loops bridged again.
    # A recut stands only if every seam loop is still bridged and the junction stays
    # edge-manifold (the remeshing needs it): CesiumMan's left leg replaced by itself, recut
    # twice, bridged into a non-manifold junction that was then kept unremeshed (p05 2.3 degrees).
    bridge = bridged(Vc, Fc)
    for _ in range(params.bridge_recuts):
        JV, JF, nI, keys, nb, edge, fans = bridge
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
        before = {k: info[k] for k in ("unmatched_preserved_loops", "unmatched_iso_loops", "orientation_warnings")}
        again = bridged(Vc2, Fc2)
        if (len(again[1]) == 0 or info["unmatched_preserved_loops"] > before["unmatched_preserved_loops"]
                or not is_edge_manifold(again[1])):
            info.update(before)
            info["bridge_recuts_rejected"] = info.get("bridge_recuts_rejected", 0) + 1
            break
        Vc, Fc, bridge = Vc2, Fc2, again
        info["bridge_recuts"] = info.get("bridge_recuts", 0) + 1
    JV, JF, nI, keys, nb, edge, fans = bridge
    timings["cut_bridge"] = timings.get("cut_bridge", 0.0) + time.perf_counter() - t0
    t0 = time.perf_counter()
    # remesh the union with the preserved loops fixed (drop unused fixed vertices first)
    JV, JF, old = remove_unreferenced(JV, JF)
    isfixed = old >= nI
    fixed_keys = {v: k for k, v in keys.items()}
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
        def finish(feature_tol):
            """Remesh (keeping what strays farther than ``feature_tol``; 0: plain), smooth,
            improve (a collapse never moves the shape by more than ``tol``, on either path)."""
            U, G, nfix, (RV, RF) = _remesh_keeping_features(JV, JF, fx, target, params.remesh_iterations,
                                                            feature_tol, params.feature_rounds, points=corners,
                                                            points_tol=0.1 * h, max_insert=3.0 * h)
            U = smooth_interior(U, G, np.arange(nfix), iterations=params.taubin_iterations)
            U = _project_to_inputs(U, nfix, pres, surfaces, inputs_fields, h, params.project_voxels)
            G = flip_to_improve_angles(U, G, forbidden=forb)
            U = relocate_poor_vertices(U, G, nfix, surface=(RV, RF))
            G = flip_to_improve_angles(U, G, forbidden=forb)
            if params.collapse_poor:
                U, G = collapse_to_improve_angles(U, G, nfix, max_deviation=tol, forbidden=forb)
                G = flip_to_improve_angles(U, G, forbidden=forb)
                U = relocate_poor_vertices(U, G, nfix, surface=(RV, RF))
                G = flip_to_improve_angles(U, G, forbidden=forb)
            if len(targets):
                U = snap_to_points(U, G, nfix, targets, max_dist=0.5 * target)
                G = flip_to_improve_angles(U, G, forbidden=forb)
            if feature_tol > 0:
                # the quality moves above slide vertices along the reference, whose bridge
                # strips chord across a voxel or two: back onto the inputs where they agree
                U = _project_to_inputs(U, nfix, pres, surfaces, inputs_fields, h, params.project_voxels)
            # folds smoothed open only where that keeps the shape-keeping junction's tolerance
            U, _ = untangle(U, G, nfix, max_move=params.untangle_move * feature_tol if feature_tol > 0 else None)
            return _separate_coincident(U, G, len(fx)), G, nfix - len(fx)

        try:
            replaced = _replaced_input_vertices(pres, inputs_fields, junction_masks, preserved, grid)
            targets = _surface_input_vertices(replaced, grid, field3, h) if params.snap_input_vertices else replaced[:0]
            corners = None
            if params.keep_input_corners and tol > 0:
                corners = _input_vertices_on_surface(replaced, pres, surfaces, inputs_fields, actions, band, 0.1 * h)
            U, G, nfeat = finish(tol)
            info["fidelity"] = bool(tol > 0)
            info["fidelity_tolerance"] = float(tol)
            angle = _angle_p05(U, G)
            if tol > 0 and angle < params.min_angle_p05:
                # fidelity never at the price of slivers: the features stand only while the
                # junction's 5th-percentile minimum angle stays at the acceptance level, or is
                # no worse than the plain remeshing's. Where the plain remeshing loses more of
                # the shape than a looser tolerance allows, that looser tolerance (fewer kept
                # features) is tried first; keeping less, it may cost little. (Folds do not
                # choose: a fold-free plain junction cost RiggedFigure's legs, replaced by
                # themselves, 1.4% of the diagonal against 0.08%.)
                U0, G0, _ = finish(0.0)
                plain_angle = _angle_p05(U0, G0)
                lost = np.sqrt(igl.point_mesh_squared_distance(JV, U0, G0)[0]).max()  # JV: the reference
                info["plain_deviation"] = float(lost)
                chosen = False
                for loose in [tol * f for f in params.fidelity_relax]:
                    if lost <= loose:
                        break
                    U1, G1, n1 = finish(loose)
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
            info["self_intersections"] = int(len(intersecting_face_pairs(U, G)))
            info["feature_vertices"] = int(nfeat)
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


