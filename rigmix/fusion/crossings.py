"""Crossing faces at the junction, repaired: the fused surface must not pass through itself.

Helper of :func:`rigmix.fusion.fuse_surfaces`. The remeshed junction can fold through itself
(a projection or an inserted feature point pulls a vertex across its neighbours), slice a
nearly parallel kept face (the junction a hair from the input surface), or wrap around a thin
kept part between two seams. :func:`repair_crossings` finds the crossing pairs with a broad
phase over the junction faces against the junction and the kept faces near it
(:func:`.meshutil.intersecting_face_pairs`, the report's own count) and resolves them in a
bounded number of rounds, each step kept only if the surface crosses itself less after it and
the junction's triangles stay as good (5th percentile of the minimum angles):

1. evict (:func:`_evict`): movable junction vertices inside a closed kept part the junction
   crosses (a modular character's rigid piece, :func:`kept_parts`) go out to its surface;
2. untangle (:func:`_smooth_apart`): the movable corners of the crossing faces, and from the
   third round their neighbours, take umbrella-smoothing steps, as few as remove the
   crossings: a fold opens with the least change of shape;
3. clear (:func:`_clear_parts`): a junction face that a kept piece pokes through moves along
   its normal, off the side where the piece lies, by the depth of the piece's vertices behind it;
4. push (:func:`_push_apart`): the movable corners of a face that slices another go across the
   other face's plane, to the side where most of the face lies;
5. release (:func:`_release`, from the second round): kept faces in the way of what is left
   (the kept faces crossed, those around junction corners that cannot move, and a ring more
   each round) join the junction, so that the steps above may move their vertices; they
   stay in the junction only if that lowers the count.

Only vertices move: faces, and so the surface's closedness and manifoldness, never change. A
vertex on a kept face, on an open border or on a non-manifold edge never moves.

Where those steps leave crossings the inputs did not have, :func:`repair_junction` looks for
knots of the junction: where two junction faces one ring apart cross (a crumpled cluster of tiny
triangles, folded over itself, that no vertex move untangles), the ring of faces around them
(:func:`knot_regions`) is filled again as a fan from one new vertex (:func:`fan_fill`), where that
lowers the junction's crossings, shares no edge more than twice and keeps its triangles as good;
the repair then runs again on the refilled junction, which is kept only if it leaves fewer such
crossings than the first. Where some are still left, edge flips (:func:`flip_apart`) give two
junction faces of a pair the other diagonal of their quad where that takes them out of
crossings and keeps the junction's triangles as good: a fold of two slivers between vertices
that cannot move (all on the junction's border) has no other way out. Last, where the junction's
triangles are worse than the floor (5th percentile of minimum angles), edge flips of nearly flat
quads (:func:`flip_for_angles`) give its slivers the diagonal with larger angles, crossing no
more than before. Pairs with a
kept face that crosses its own input (overlapping parts of a modular character: a shoulder
pad through the arm it covered, which the junction replaces) are counted but not worked on.
Every step is deterministic (no threads, no random choice).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from .meshutil import (
    boundary_halfedges,
    boxes_meet,
    cross3,
    edge_counts,
    edges_to_loops,
    intersecting_face_pairs,
    triangle_min_angles,
    undirected_edges,
    unique_rows,
    vertex_adjacency,
    vertex_components,
)

log = logging.getLogger(__name__)

__all__ = ["CrossingRepair", "JunctionRepair", "fan_fill", "flip_apart", "flip_for_angles", "kept_parts",
           "knot_regions", "layer_faces", "near_faces", "repair_crossings", "repair_junction"]

#: Faces within this many target edges of the junction are looked at (the broad phase's reach:
#: a repair moves vertices by about an edge).
NEAR_EDGES = 3.0

#: A smoothing or push sequence stops after this many steps that do no better than the best.
PATIENCE = 3

#: Halvings of an untangling move in search of the least move that does as well.
BISECTIONS = 4

#: Pushed corners end this many target edges beyond the other face's plane.
PUSH_MARGIN = 0.05

#: A clearing step (:func:`_clear_parts`) moves no corner further than this many target edges.
CLEAR_EDGES = 1.0

#: Corners taken out of a closed kept part end this many target edges beyond its surface.
EVICT_MARGIN = 0.25

#: A knot (:func:`knot_regions`) is looked for within at most this many rings around its pair.
KNOT_RINGS = 3

#: Passes of :func:`flip_apart` at most; and how many rings of faces around the crossings left
#: may flip.
FLIP_PASSES = 16
FLIP_RINGS = 3

#: Passes of :func:`flip_for_angles` at most; and the most a quad it flips may bend (degrees
#: between its two faces' normals, before and after): a flip of a flatter quad changes the
#: triangles and not the surface's shape.
ANGLE_FLIP_PASSES = 8
ANGLE_FLIP_BEND = 20.0


@dataclass(frozen=True)
class CrossingRepair:
    """The surface after :func:`repair_crossings` (same faces, vertices moved).

    Attributes
    ----------
    V : (n, 3) float64
        Positions; only movable vertices differ from the input's.
    released : (m,) bool
        Kept faces that joined the junction (their vertices may have moved).
    found, left : int
        Crossing pairs before and after.
    layered : int
        Of those left, pairs with a kept face that crosses its own input (not worked on).
    rounds, steps : int
        Rounds run; smoothing and push steps that stood.
    made : (m,) bool
        Faces in a pair left that is not layered (a crossing the inputs did not have).
    layered_faces : (m,) bool
        Kept faces that cross their own input (their pairs are not worked on).
    """

    V: np.ndarray
    released: np.ndarray
    found: int
    left: int
    layered: int
    rounds: int
    steps: int
    made: np.ndarray
    layered_faces: np.ndarray | None = None


class _State:
    """What a repair changes: positions, movable vertices, junction (``check``) faces; and what
    it looks at: faces near the junction, kept faces that cross their own input."""

    def __init__(self, V, F, movable, check, layered, releasable, pinned, reach, span, parts=None):
        self.V, self.F = V, F
        self.movable, self.check = movable, check
        self.layered, self.releasable, self.pinned = layered, releasable, pinned
        # kept part of each face apart from the junction, or -1, and whether each part is closed
        self.part, self.closed = (np.full(len(F), -1), np.zeros(0, bool)) if parts is None else parts
        self.reach = reach  # a moved face is tested against the faces within about this distance
        self.span = span  # the faces within about this distance of the junction are looked at
        self.look()

    def look(self):
        """The faces looked at: those within ``span`` of a ``check`` face, at the current
        positions (every face that crosses a ``check`` face is among them)."""
        self.near = near_faces(self.V, self.F, self.check, self.span)

    def snapshot(self):
        return self.V, self.movable, self.check, self.near

    def restore(self, snap):
        self.V, self.movable, self.check, self.near = snap

    def pairs(self, V=None, old=None, moved=None):
        """Crossing pairs among the faces near the junction, at least one a ``check`` face.

        With ``old`` (the pairs before) and ``moved`` (``(n,)`` bool, the vertices that moved
        since), only the faces on moved vertices are tested again.
        """
        V = self.V if V is None else V
        sub = np.flatnonzero(self.near)
        if old is None or moved is None:
            p = intersecting_face_pairs(V, self.F[sub], np.flatnonzero(self.check[sub]))
            return _canonical(sub[p])
        touched = moved[self.F].any(axis=1)
        keep = old[~(touched[old[:, 0]] | touched[old[:, 1]])]
        sub = sub[near_faces(V, self.F[sub], touched[sub], self.reach)]  # what the moved faces may reach
        fresh = sub[intersecting_face_pairs(V, self.F[sub], np.flatnonzero(touched[sub]))]
        fresh = fresh[self.check[fresh[:, 0]] | self.check[fresh[:, 1]]]
        return _canonical(np.concatenate([keep, fresh]))

    def targets(self, pairs):
        """The pairs the repair works on: those without a ``layered`` face."""
        return pairs[~(self.layered[pairs[:, 0]] | self.layered[pairs[:, 1]])]

    def angle_p05(self, V):
        """5th percentile of the minimum angles of the junction faces (degrees)."""
        T = self.F[self.check]
        return float(np.percentile(triangle_min_angles(V, T), 5)) if len(T) else 90.0

    def better(self, V, p, best_pairs, floor):
        """Whether ``V`` (crossing pairs ``p``) beats the best so far: fewer pairs, and the
        junction's angles no worse than ``floor``."""
        return len(p) < len(best_pairs) and self.angle_p05(V) >= floor


def _canonical(P):
    """Pairs ``(p, 2)`` as sorted rows, each once, in order."""
    if len(P) == 0:
        return np.zeros((0, 2), np.int64)
    return unique_rows(np.sort(np.asarray(P, np.int64), axis=1))


def _box_cells(lo, hi, cell):
    """Cells of a grid of ``cell``-sized cells (from the origin) that each box touches.

    Returns
    -------
    box : (k,) int64, ijk : (k, 3) int64
        Box ``box[i]`` touches cell ``ijk[i]``.
    """
    c0 = np.floor(lo / cell).astype(np.int64)
    n = np.floor(hi / cell).astype(np.int64) - c0 + 1
    count = n.prod(axis=1)
    box = np.repeat(np.arange(len(lo)), count)
    k = np.arange(len(box)) - np.repeat(np.cumsum(count) - count, count)
    nx, ny = n[box, 0], n[box, 1]
    ijk = c0[box] + np.stack([k % nx, (k // nx) % ny, k // (nx * ny)], axis=1)
    return box, ijk


#: Boxes wider than this many grid cells are met box by box (:func:`.meshutil.boxes_meet`), not by cells.
BIG_CELLS = 4


def near_faces(V, F, query, margin):
    """``(m,)`` bool: the ``query`` faces and the faces within about ``margin`` of one (their
    boxes touch a cell of a ``margin`` grid next to one a ``query`` face touches; a box much
    larger than a cell is compared with the query boxes directly).

    ``V`` ``(n, 3)``, ``F`` ``(m, 3)``, ``query`` ``(m,)`` bool; ``margin`` in the units of ``V``.
    The crossing repair's neighbourhood of the faces it moves: a superset of the faces within
    ``margin`` of a query face, never missing one.
    """
    T = V[F]
    lo, hi = T.min(axis=1), T.max(axis=1)
    near = query.copy()
    if not query.any() or margin <= 0:
        return near
    big = ((hi - lo) / margin).max(axis=1) > BIG_CELLS
    q_small, q_big = np.flatnonzero(query & ~big), np.flatnonzero(query & big)
    small = np.flatnonzero(~big)
    if len(q_small):
        _, qc = _box_cells(lo[q_small], hi[q_small], margin)
        base = qc.min(axis=0) - 1  # integer keys of the cells around the query's, all non-negative
        dims = qc.max(axis=0) - base + 2
        # only a box with a cell in that window can touch a marked cell: the others are never
        # split into cells (the cells are those _box_cells gives, floor(corner / margin))
        window = np.all((np.floor(hi[small] / margin).astype(np.int64) >= base)
                        & (np.floor(lo[small] / margin).astype(np.int64) < base + dims), axis=1)
        cand = small[window]
        box, ijk = _box_cells(lo[cand], hi[cand], margin)
        inside = np.all((ijk >= base) & (ijk < base + dims), axis=1)
        box, ijk = box[inside], ijk[inside]
        off = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)

        def key(c):
            c = c - base
            return (c[..., 0] * dims[1] + c[..., 1]) * dims[2] + c[..., 2]

        marked = np.unique(key(qc[:, None, :] + off[None]))
        near[cand[box[np.isin(key(ijk), marked)]]] = True
    qi = np.flatnonzero(query)
    bigs = np.flatnonzero(big)
    near[bigs] |= boxes_meet(lo[bigs], hi[bigs], lo[qi], hi[qi], margin)
    near[small] |= boxes_meet(lo[small], hi[small], lo[q_big], hi[q_big], margin)
    return near


def _smooth_apart(S: _State, pairs, work, *, ring, steps, step, floor):
    """Umbrella-smoothing steps on the movable corners of the faces of the crossing pairs
    ``work`` (of ``pairs``, all of them) and ``ring`` rings of neighbours; the first step with
    no pair of ``work`` left, or else the one with fewest pairs (:data:`PATIENCE`).

    Returns
    -------
    V : (n, 3) float64, pairs : (p, 2) int64, steps : int
        Unchanged with ``steps == 0`` when no step does better.
    """
    A = vertex_adjacency(S.F, len(S.V)).astype(np.float64).tocsr()
    deg = np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1.0)
    move = np.zeros(len(S.V), bool)
    move[S.F[work.ravel()].ravel()] = True
    for _ in range(ring):
        move |= (A @ move.astype(np.float64)) > 0
    move &= S.movable
    best = (S.V, pairs, 0)
    if not move.any():
        return best
    U = S.V.copy()
    for k in range(1, steps + 1):
        mean = (A @ U) / deg[:, None]
        U[move] += step * (mean[move] - U[move])
        p = S.pairs(U, pairs, move)
        if S.better(U, p, best[1], floor):
            best = (U.copy(), p, k)
        if len(S.targets(p)) == 0 or k - best[2] >= PATIENCE:
            break
    return best


def _push_apart(S: _State, pairs, work, *, margin, steps, floor):
    """Push the movable corners of each face of the crossing pairs ``work`` (of ``pairs``, all
    of them) across the other face's plane, to the side where most of the face lies, by the
    corner's distance and ``margin``; the first of ``steps`` pushes with no pair of ``work``
    left, or else the one with fewest pairs (:data:`PATIENCE`).

    A junction face that slices a nearly parallel face (the two surfaces a hair apart) has no
    fold for smoothing to open; a push along the normal separates them with the least move.

    Returns
    -------
    V : (n, 3) float64, pairs : (p, 2) int64, steps : int
        Unchanged with ``steps == 0`` when no push does better.
    """
    best = (S.V, pairs, 0)
    U, p = S.V.copy(), pairs
    for k in range(1, steps + 1):
        move = np.zeros_like(U)
        hits = np.zeros(len(U))
        for x, y in ((work[:, 0], work[:, 1]), (work[:, 1], work[:, 0])):
            P = U[S.F[y]]
            n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
            d = np.einsum("pkc,pc->pk", U[S.F[x]] - P[:, :1], n)  # (p, 3): x's corners from y's plane
            side = np.where(d.sum(axis=1) >= 0, 1.0, -1.0)  # where most of x lies
            wrong = (d * side[:, None] < margin) & S.movable[S.F[x]]
            shift = (side[:, None] * margin - d)[:, :, None] * n[:, None, :]  # (p, 3, 3)
            np.add.at(move, S.F[x][wrong], shift[wrong])
            np.add.at(hits, S.F[x][wrong], 1.0)
        if not hits.any():
            break
        U = U + move / np.maximum(hits, 1.0)[:, None]
        p = S.pairs(U, p, hits > 0)
        if S.better(U, p, best[1], floor):
            best = (U.copy(), p, k)
        work = S.targets(p)
        if len(work) == 0 or k - best[2] >= PATIENCE:
            break
    return best


def _release(S: _State, work, ring):
    """Kept faces in the way join the junction: the kept faces of the crossing pairs ``work``,
    those around the corners of their junction faces that cannot move, and ``ring`` rings of
    kept faces around those (``releasable`` ones only). Their vertices that no other kept face
    uses, on no open border nor non-manifold edge, become movable.

    Returns
    -------
    int
        Faces released.
    """
    f = np.unique(work.ravel())
    corners = S.F[f[S.check[f]]].ravel()
    corners = np.unique(corners[~S.movable[corners]])
    rel = np.zeros(len(S.F), bool)
    rel[f] = True
    rel |= np.isin(S.F, corners).any(axis=1)
    rel &= S.releasable & ~S.check
    for _ in range(ring):
        touch = np.zeros(len(S.V), bool)
        touch[S.F[rel].ravel()] = True
        rel |= touch[S.F].any(axis=1) & S.releasable & ~S.check
    if not rel.any():
        return 0
    S.check = S.check | rel
    S.look()
    on_kept = np.zeros(len(S.V), bool)
    on_kept[S.F[~S.check].ravel()] = True
    touched = np.zeros(len(S.V), bool)
    touched[S.F[rel].ravel()] = True
    S.movable = S.movable | (touched & ~on_kept & ~S.pinned)
    return int(rel.sum())


def _least_move(S: _State, pairs, U, p, floor):
    """The shortest way towards ``U`` (crossing pairs ``p``) from ``S.V`` (``pairs``) that does
    as well: bisection on the fraction ``t`` of the move (:data:`BISECTIONS` halvings).

    Returns
    -------
    U : (n, 3) float64, p : (q, 2) int64
    """
    moved = np.any(U != S.V, axis=1)
    lo, hi = 0.0, 1.0
    for _ in range(BISECTIONS):
        t = 0.5 * (lo + hi)
        W = S.V + t * (U - S.V)
        q = S.pairs(W, pairs, moved)
        if len(q) <= len(p) and S.angle_p05(W) >= floor:
            hi, U, p = t, W, q
        else:
            lo = t
    return U, p


def kept_parts(F, n, fixed):
    """The kept parts of the surface apart from the junction: connected components (by shared
    vertices) whose vertices are all ``fixed`` ``(n,) bool`` (kept vertices that never move), a
    modular character's separate pieces.

    Returns
    -------
    part : (m,) int64
        Each face's part, or -1 (a face of a component with a junction vertex).
    closed : (k,) bool
        Per part label, whether it is closed (no boundary or non-manifold edge): a rigid piece
        with an inside.
    """
    F = np.asarray(F, np.int64)
    labels = vertex_components(F, n)
    face_label = labels[F[:, 0]]
    k = int(labels.max()) + 1 if len(labels) else 0
    moving = np.zeros(k, bool)
    moving[labels[~np.asarray(fixed, bool)]] = True
    closed = np.ones(k, bool)
    uE, cnt = edge_counts(F)
    closed[labels[uE[cnt != 2, 0]]] = False
    return np.where(moving[face_label], -1, face_label), closed & ~moving


def layer_faces(V, F, kept, faces, *, reach):
    """The faces of wholly kept pieces layered into their input's surface where the junction
    replaced it: a modular character's sleeve through the arm it covers, a plate through the hip.

    A kept piece (a connected component of ``(V, F)`` whose faces are all ``kept``) that passes
    through its input's surface (a face of another component, or a replaced face) within
    ``reach`` of the replaced surface is layered into the surface the junction continues there;
    the junction, within ``reach`` of that surface, crosses the piece along about the same curve,
    but at the piece's faces beside the ones that crossed, since the junction is remeshed and
    blended. Those faces are the piece's faces within ``reach`` of the replaced surface and
    connected, through such faces, to one that passes through its input's surface there.

    Parameters
    ----------
    V : (n, 3) float array, F : (m, 3) int array
        An input mesh welded by position.
    kept : (m,) bool
        Faces kept in the output; the others are the replaced surface.
    faces : (k,) int array
        Faces asked about: only the pieces holding them are looked at.
    reach : float
        Same unit as ``V``: how far from the replaced surface the junction lies where it crosses
        the pieces.

    Returns
    -------
    (k,) bool
        Whether each of ``faces`` is such a face.
    """
    import igl

    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    kept = np.asarray(kept, bool)
    faces = np.asarray(faces, np.int64)
    out = np.zeros(len(faces), bool)
    if not len(faces) or kept.all() or not kept.any():
        return out
    labels = vertex_components(F, len(V))
    face_label = labels[F[:, 0]]
    whole = np.ones(int(labels.max()) + 1, bool)
    whole[face_label[~kept]] = False  # a component with a replaced face is no piece
    asked = np.unique(face_label[faces])
    asked = asked[whole[asked]]
    if not len(asked):
        return out
    piece = np.flatnonzero(np.isin(face_label, asked))
    # distance of each piece face to the replaced surface: the least of its corners' and centre's
    P = np.concatenate([V[F[piece]], V[F[piece]].mean(axis=1, keepdims=True)], axis=1)
    d2, _, _ = igl.point_mesh_squared_distance(P.reshape(-1, 3), V, F[~kept])
    near = np.zeros(len(F), bool)
    near[piece[np.sqrt(d2).reshape(-1, 4).min(axis=1) <= reach]] = True
    if not near.any():
        return out
    own = intersecting_face_pairs(V, F, np.flatnonzero(near))
    through = ~kept[own] | (face_label[own] != face_label[own[:, ::-1]])  # the other face: replaced or not the piece's
    layered = np.zeros(len(F), bool)
    layered[own[:, 0][through[:, 1]]] = True
    layered[own[:, 1][through[:, 0]]] = True
    layered &= near
    if not layered.any():
        return out
    # the near faces connected to one layered (through shared vertices)
    sub = np.flatnonzero(near)
    _, vlab = connected_components(vertex_adjacency(F[sub], len(V)), directed=False)
    seeded = np.unique(vlab[F[layered, 0]])
    region = np.zeros(len(F), bool)
    region[sub[np.isin(vlab[F[sub, 0]], seeded)]] = True
    return region[faces]


def _evict(S: _State, pairs, work, *, margin, floor):
    """Take the movable junction vertices out of the closed kept parts that the crossing pairs
    ``work`` (of ``pairs``) cross (:func:`kept_parts`): each vertex inside a part (winding
    number above 1/2) goes to the part's closest point and ``margin`` beyond, away from it.

    The junction went around a rigid piece but cut a corner of it: no fold to smooth open, and a
    push across one face's plane runs into the next face of the piece.

    Returns
    -------
    V : (n, 3) float64, pairs : (p, 2) int64, moved : bool
    """
    import igl

    parts = np.unique(S.part[work.ravel()])
    parts = parts[parts >= 0]
    parts = parts[S.closed[parts]]
    if not len(parts):
        return S.V, pairs, False
    U = S.V.copy()
    moved = np.zeros(len(U), bool)
    cand = np.zeros(len(U), bool)
    cand[S.F[S.check].ravel()] = True
    cand &= S.movable
    for part in parts:
        Fs = S.F[S.part == part]
        X = S.V[Fs].reshape(-1, 3)
        lo, hi = X.min(axis=0) - margin, X.max(axis=0) + margin
        q = np.flatnonzero(cand & np.all((S.V >= lo) & (S.V <= hi), axis=1))
        if not len(q):
            continue
        w = igl.fast_winding_number(S.V, Fs, S.V[q])
        q = q[w > 0.5]
        if not len(q):
            continue
        _, _, C = igl.point_mesh_squared_distance(S.V[q], S.V, Fs)
        d = C - S.V[q]
        n = np.linalg.norm(d, axis=1, keepdims=True)
        U[q] = C + margin * d / np.maximum(n, 1e-300)
        moved[q] = True
    if not moved.any():
        return S.V, pairs, False
    p = S.pairs(U, pairs, moved)
    if S.better(U, p, pairs, floor):
        return U, p, True
    return S.V, pairs, False


def _clear_parts(S: _State, pairs, work, *, margin, steps, floor):
    """Move each junction face of the crossing pairs ``work`` with a kept part
    (:func:`kept_parts`, closed or not) off the part: along its normal, away from the side where the
    part's nearby vertices mostly lie, by the depth of the part's vertices that poke through it
    and ``margin``; the first of ``steps`` moves with no pair of ``work`` left, or else the one
    with fewest pairs (:data:`PATIENCE`).

    A junction made around a rigid piece cuts its corners where the triangles are coarser than
    the piece's curvature: the piece's vertices poke through the face, none of the face's
    corners is inside the piece, and a push across one face's plane of the piece runs into the
    next one.

    Returns
    -------
    V : (n, 3) float64, pairs : (p, 2) int64, steps : int
    """
    best = (S.V, pairs, 0)
    U, p = S.V.copy(), pairs
    part_vertices = {}
    for k in range(1, steps + 1):
        a, b = work[:, 0], work[:, 1]
        x = np.where(S.check[a], a, b)  # the junction face
        y = np.where(S.check[a], b, a)
        sel = (S.part[y] >= 0) & ~S.check[y]
        if not sel.any():
            break
        for q in np.unique(S.part[y[sel]]):
            if q not in part_vertices:
                part_vertices[q] = np.unique(S.F[S.part == q].ravel())
        move = np.zeros_like(U)
        hits = np.zeros(len(U))
        for f in np.unique(x[sel]):
            parts = np.unique(S.part[y[sel & (x == f)]])
            P = U[S.F[f]]
            n = np.cross(P[1] - P[0], P[2] - P[0])
            area2 = np.linalg.norm(n)
            if area2 <= 0:
                continue
            n /= area2
            c = P.mean(axis=0)
            radius = np.linalg.norm(P - c, axis=1).max() + S.reach
            X = U[np.concatenate([part_vertices[q] for q in parts])]
            X = X[np.linalg.norm(X - c, axis=1) <= radius]
            if not len(X):
                continue
            h = (X - c) @ n
            side = 1.0 if h.sum() >= 0 else -1.0
            depth = max(float((-side * h).max()), 0.0)
            shift = -side * (depth + margin) * n
            corners = S.F[f][S.movable[S.F[f]]]
            move[corners] += shift
            hits[corners] += 1.0
        if not hits.any():
            break
        U = U + move / np.maximum(hits, 1.0)[:, None]
        # a piece sunk deep under the junction is not the junction's to go around: no corner
        # goes further than CLEAR_EDGES target edges from where the clearing started
        d = U - S.V
        r = np.linalg.norm(d, axis=1)
        far = r > CLEAR_EDGES * S.reach
        U[far] = S.V[far] + d[far] * (CLEAR_EDGES * S.reach / r[far])[:, None]
        p = S.pairs(U, p, hits > 0)
        if S.better(U, p, best[1], floor):
            best = (U.copy(), p, k)
        work = S.targets(p)
        if len(work) == 0 or k - best[2] >= PATIENCE:
            break
    return best


def _untangle(S: _State, pairs, *, ring, steps, step, margin, floor):
    """Smoothing then pushing (:func:`_smooth_apart`, :func:`_push_apart`) on the pairs the
    repair works on, each move cut back to the least that does as well (:func:`_least_move`).
    Returns ``(pairs, steps that stood)`` and updates ``S.V``."""
    done = 0
    work = S.targets(pairs)
    if len(work):
        U, p, moved = _evict(S, pairs, work, margin=EVICT_MARGIN * S.reach, floor=floor)
        if moved:
            S.V, pairs, done = U, p, done + 1
    for tier in ("smooth", "clear", "push"):
        work = S.targets(pairs)
        if len(work) == 0:
            break
        if tier == "smooth":
            U, p, k = _smooth_apart(S, pairs, work, ring=ring, steps=steps, step=step, floor=floor)
        elif tier == "clear":
            U, p, k = _clear_parts(S, pairs, work, margin=PUSH_MARGIN * S.reach, steps=steps, floor=floor)
        else:
            U, p, k = _push_apart(S, pairs, work, margin=margin, steps=steps, floor=floor)
        if k:
            U, p = _least_move(S, pairs, U, p, floor)
            S.V, pairs, done = U, p, done + k
    return pairs, done


def repair_crossings(V, F, movable, check, *, target, releasable=None, layered=None, rounds=6, steps=8,
                     step=0.5, min_angle=20.0) -> CrossingRepair:
    """Resolve the pairs of faces that cross each other at the junction (see the module).

    Parameters
    ----------
    V : (n, 3) float array
        The surface welded by position (a crossing is counted, and a corner shared, by index).
    F : (m, 3) int array
    movable : (n,) bool
        Vertices that may move (generated junction vertices that no kept face uses).
    check : (m,) bool
        Faces whose crossings count (the report's junction faces).
    target : float
        The junction's edge length, same unit as ``V``: the reach of the broad phase and the
        push margin are in these.
    releasable : (m,) bool, optional
        Kept faces that may join the junction (default none).
    layered : callable, optional
        ``layered(faces)``: ``(k,) bool`` for the kept faces ``faces`` ``(k,)``, whether each
        crosses a face of its own input; asked once, about the kept faces near the junction,
        and only when something crosses (default: none does).
    rounds : int
        Rounds at most (fewer after two rounds in a row that lower nothing); round ``r`` smooths
        ``r // 2`` rings beyond the crossing faces and releases ``r - 1`` rings of kept faces
        around them.
    steps, step : int, float
        Smoothing and push steps per round at most; smoothing step size (fraction of the way
        to the mean of the neighbours).
    min_angle : float
        Degrees; a step stands only if the junction's 5th percentile of minimum angles stays at
        least the smaller of this and its value before the repair.

    Returns
    -------
    CrossingRepair
    """
    V = np.array(V, np.float64)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    m = len(F)
    check = np.asarray(check, bool).copy()
    releasable = np.zeros(m, bool) if releasable is None else np.asarray(releasable, bool) & ~check
    uE, cnt = edge_counts(F)
    pinned = np.zeros(len(V), bool)  # borders and non-manifold edges keep their positions
    pinned[uE[cnt != 2].ravel()] = True
    movable = np.asarray(movable, bool) & ~pinned
    S = _State(V, F, movable, check, np.zeros(m, bool), releasable, pinned, reach=target, span=NEAR_EDGES * target,
               parts=kept_parts(F, len(V), ~np.asarray(movable, bool)))
    pairs = S.pairs()
    found = len(pairs)
    if found and layered is not None:
        ask = np.flatnonzero(S.near & ~check)
        S.layered[ask] = np.asarray(layered(ask), bool)
        S.releasable = releasable & ~S.layered
    floor = min(min_angle, S.angle_p05(V))
    kw = {"steps": steps, "step": step, "margin": PUSH_MARGIN * target}
    n_steps = done = idle = 0
    for r in range(rounds):
        if len(S.targets(pairs)) == 0 or idle == 2:  # two rounds in a row lowered nothing
            break
        done, start = r + 1, len(pairs)
        pairs, k = _untangle(S, pairs, ring=r // 2, floor=floor, **kw)
        n_steps += k
        if r > 0 and len(S.targets(pairs)):
            snap = S.snapshot()
            if _release(S, S.targets(pairs), r - 1):
                # released faces count from now on: whatever they cross is counted again
                p, k = _untangle(S, S.pairs(), ring=r // 2, floor=min(floor, S.angle_p05(S.V)), **kw)
                if len(p) < len(pairs):
                    pairs, n_steps = p, n_steps + k
                else:  # the released faces did not help: kept again
                    S.restore(snap)
        idle = idle + 1 if len(pairs) >= start else 0
    if n_steps:  # counted again where the moves took the junction
        S.look()
        pairs = S.pairs()
    left = len(pairs)
    made = np.zeros(m, bool)
    made[S.targets(pairs).ravel()] = True
    n_layered = left - len(S.targets(pairs))
    released = S.check & ~check
    if found:
        log.info("fusion: %d crossing face pairs at the junction, %d left (%d with a kept face crossing its input; "
                 "%d rounds, %d steps, %d kept faces released)", found, left, n_layered, done, n_steps,
                 int(released.sum()))
    return CrossingRepair(V=S.V, released=released, found=int(found), left=int(left), layered=int(n_layered),
                          rounds=done, steps=n_steps, made=made, layered_faces=S.layered.copy())


def knot_regions(F, n, fixed, pairs, *, rings=KNOT_RINGS) -> list:
    """The knots around crossing pairs of faces that lie one ring apart.

    For each pair ``(a, b)`` of ``pairs`` where a corner of ``b`` is a corner of ``a`` or its
    neighbour, the faces whose corners all lie within ``k`` rings of the pair's corners, for the
    smallest ``k <= rings`` where they form one region bounded by a single closed loop without a
    repeated vertex, with at least one inner vertex, every inner vertex free to move (not
    ``fixed``) and used by the region's faces only. Regions never share a face.

    Parameters
    ----------
    F : (m, 3) int array
        Faces over ``n`` vertices (welded by position).
    fixed : (n,) bool
        Vertices that must keep their place and their faces (kept vertices, borders).
    pairs : (p, 2) int array
        Crossing face pairs.

    Returns
    -------
    list of (faces, loop)
        ``faces`` ``(r,)`` int64 the region's faces, ``loop`` ``(k,)`` int64 its boundary, in
        the direction of its faces' edges.
    """
    F = np.asarray(F, np.int64).reshape(-1, 3)
    A = (vertex_adjacency(F, n) + sparse.identity(n, format="csr")).tocsr()
    degree = np.bincount(F.ravel(), minlength=n)  # faces per vertex
    taken = np.zeros(len(F), bool)
    out = []
    for a, b in np.asarray(pairs, np.int64).reshape(-1, 2):
        if taken[a] or taken[b]:
            continue
        near = np.zeros(n)
        near[F[a]] = 1.0
        if not ((A @ near) > 0)[F[b]].any():
            continue
        seed = np.zeros(n)
        seed[F[[a, b]].ravel()] = 1.0
        for _ in range(rings):
            seed = ((A @ seed) > 0).astype(np.float64)
            R = np.flatnonzero((seed[F] > 0).all(axis=1))
            if taken[R].any():
                break
            loops, closed = edges_to_loops(boundary_halfedges(F[R]))
            if len(loops) != 1 or not closed[0] or len(np.unique(loops[0])) != len(loops[0]):
                continue
            inner = np.setdiff1d(np.unique(F[R]), loops[0])
            in_region = np.bincount(F[R].ravel(), minlength=n)
            if len(inner) and not fixed[inner].any() and np.all(in_region[inner] == degree[inner]):
                out.append((R, loops[0]))
                taken[R] = True
                break
    return out


def fan_fill(V, F, regions):
    """Each region of ``regions`` (:func:`knot_regions`) replaced by a fan of triangles from a new
    vertex at the mean of its boundary loop to each loop edge (the faces' orientation kept).

    Returns
    -------
    V2 : (n + r, 3) float64
        ``V`` then one vertex per region.
    F2 : (m2, 3) int64
        The faces outside the regions, in order, then the fans.
    origin : (m2,) int64
        The face of ``F`` each face of ``F2`` is or replaces (a fan: its region's first face).
    """
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    keep = np.ones(len(F), bool)
    centres, fans, origin = [], [], []
    for R, loop in regions:
        keep[R] = False
        centres.append(V[loop].mean(axis=0))
        fans.append(np.stack([loop, np.roll(loop, -1), np.full(len(loop), len(V) + len(centres) - 1)], axis=1))
        origin.append(np.full(len(loop), R[0], np.int64))
    V2 = np.concatenate([V, np.reshape(centres, (-1, 3))])
    F2 = np.concatenate([F[keep]] + fans).astype(np.int64)
    return V2, F2, np.concatenate([np.flatnonzero(keep)] + origin).astype(np.int64)


def _untie_knots(Vw, Fw, mK, fixed, min_angle):
    """The junction faces ``Fw[mK:]`` with their knots filled again (:func:`knot_regions`,
    :func:`fan_fill`) where that lowers the crossing pairs among them, shares no edge of the
    whole surface more than twice, and keeps the junction's 5th percentile of minimum angles at
    least the smaller of ``min_angle`` and its value before; else ``None``.

    Returns
    -------
    None or (V2, F2, origin)
        The surface (kept faces first, unchanged) and, per junction face, the junction face of
        ``Fw[mK:]`` it is or replaces.
    """
    JF = Fw[mK:]
    pairs = intersecting_face_pairs(Vw, JF)
    if not len(pairs):
        return None
    regions = knot_regions(JF, len(Vw), fixed, pairs)
    if not regions:
        return None
    V2, JF2, origin = fan_fill(Vw, JF, regions)
    F2 = np.concatenate([Fw[:mK], JF2])
    floor = min(min_angle, float(np.percentile(triangle_min_angles(Vw, JF), 5)))
    if (len(intersecting_face_pairs(V2, JF2)) >= len(pairs)
            or np.count_nonzero(edge_counts(F2)[1] > 2) > np.count_nonzero(edge_counts(Fw)[1] > 2)
            or float(np.percentile(triangle_min_angles(V2, JF2), 5)) < floor):
        return None
    log.info("fusion: %d knots of the junction filled again (%d faces -> %d)", len(regions),
             sum(len(R) for R, _ in regions), sum(len(loop) for _, loop in regions))
    return V2, F2, origin


def _face_normals(T):
    n = cross3(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _window_crossings(V, W, skip, reach, faces, extra=None):
    """Crossing pairs ``(p, 2)`` among the window faces ``W`` (``len(W) + i`` the face
    ``extra[i]``) with a face of ``faces``, none ``skip``, none between two ``extra`` faces."""
    X = W if extra is None else np.concatenate([W, extra])
    q = np.zeros(len(X), bool)
    q[faces] = True
    sub = np.flatnonzero(near_faces(V, X, q, reach))
    p = sub[intersecting_face_pairs(V, X[sub], np.flatnonzero(q[sub]))]
    out = np.concatenate([skip, np.zeros(len(X) - len(W), bool)])
    p = p[~(out[p[:, 0]] | out[p[:, 1]])]
    return p[(p < len(W)).any(axis=1)]


def _new_pair_crossings(V, W, skip, reach, news):
    """``(k,)`` int: for each of ``news`` (``(2, 3)`` face pairs, one per candidate flip), the
    crossing pairs its two faces would have with the window faces ``W`` (:func:`_window_crossings`,
    all candidates tested at once, none against another)."""
    extra = np.concatenate(news)
    p = _window_crossings(V, W, skip, reach, np.arange(len(W), len(W) + len(extra)), extra)
    return np.bincount((p.max(axis=1) - len(W)) // 2, minlength=len(news))


def _quad_box(V, new, boxes):
    """The box ``(lo, hi)`` of the quad ``new`` ``(2, 3)``, or None where it meets one of
    ``boxes`` (a quad flipped in the same pass: a candidate beside it was tested without it)."""
    qlo, qhi = V[new].min(axis=(0, 1)), V[new].max(axis=(0, 1))
    if any(np.all(qlo <= b_hi) and np.all(b_lo <= qhi) for b_lo, b_hi in boxes):
        return None
    return qlo, qhi


def _flip_candidates(V, W, can, work):
    """``(f, g, new)`` for each flip of an edge of a ``work`` face of ``W`` with a ``can`` face
    ``g`` across it: ``new`` ``(2, 3)``, the two faces over the quad's other diagonal, oriented as
    the old, where that diagonal is no edge yet, neither new face turns by 90 degrees or more from
    the old pair's mean normal, and the new pair folds by no more than 90 degrees or the old one."""
    m = len(W)
    _, uE, emap = undirected_edges(W)  # half-edge e of face f at row e m + f
    count = np.bincount(emap, minlength=len(uE))
    by_edge = np.argsort(emap, kind="stable")
    mate = np.full(3 * m, -1)  # the other half-edge of an edge of two faces
    two = np.flatnonzero(count[emap[by_edge]] == 2)
    first = two[::2] if len(two) else two
    mate[by_edge[first]], mate[by_edge[first + 1]] = by_edge[first + 1], by_edge[first]
    ukey = uE[:, 0] * len(V) + uE[:, 1]  # sorted, as uE is
    found = []
    halves = np.flatnonzero(np.tile(work, 3) & (mate >= 0))
    for h in halves[np.argsort((halves % m) * 3 + halves // m)]:  # face by face, edge by edge
        e, f = divmod(int(h), m)
        g = int(mate[h]) % m
        if not can[g]:
            continue
        u, v, w = W[f, e], W[f, (e + 1) % 3], W[f, (e + 2) % 3]
        x = int(W[g][(W[g] != u) & (W[g] != v)][0])
        diagonal = min(w, x) * len(V) + max(w, x)
        i = np.searchsorted(ukey, diagonal)
        if x == w or (i < len(ukey) and ukey[i] == diagonal):
            continue  # the other diagonal is an edge already
        new = np.array([[w, u, x], [x, v, w]])
        n_old, n_new = _face_normals(V[W[[f, g]]]), _face_normals(V[new])
        if (n_new @ n_old.sum(axis=0)).min() <= 0 or n_new[0] @ n_new[1] < min(0.0, n_old[0] @ n_old[1]):
            continue
        found.append((f, g, new))
    return found


def flip_apart(V, F, flippable, made, *, ignored=None, reach, floor, passes=FLIP_PASSES, rings=FLIP_RINGS):
    """Edge flips that take faces out of the crossing pairs left: a fold of two slivers that no
    vertex move opens often has the wrong diagonal.

    Each edge of a ``made`` face (and, once a flip stands, of the flipped faces) shared by
    exactly two ``flippable`` faces is a candidate, if its flip (the other diagonal of the two
    faces' quad) gives no edge of ``F`` twice, turns neither new face by 90 degrees or more from
    the old pair's mean normal, and folds the new pair by no more than 90 degrees or no more than
    the old one. A pass tests every candidate at once against the surface as the pass found it
    (how many crossing pairs its two new faces have, against the old two's); flips then stand in
    order of the most pairs removed, then the larger minimum angle, where they remove some, keep
    the ``flippable`` faces' 5th percentile of minimum angles at least ``floor``, and their quad
    meets no quad flipped in the same pass (tested without it). Passes repeat while one flip
    stands, at most ``passes``; only faces within ``rings`` rings of the ``made`` ones flip.

    Parameters
    ----------
    V : (n, 3) float array
        Positions (welded by position); never change.
    F : (m, 3) int array
    flippable : (m,) bool
        Faces whose connectivity may change (generated junction faces).
    made : (m,) bool
        Faces in the crossing pairs to resolve.
    ignored : (m,) bool, optional
        Faces whose pairs do not count (kept faces that cross their own input).
    reach : float
        Faces within about this distance of the flipped ones are tested (same unit as ``V``).
    floor : float
        Degrees.

    Returns
    -------
    F2 : (m, 3) int64
        ``F`` with the flipped faces rewritten in place (same count, same order).
    flipped : (m,) bool
        Faces whose corners changed.
    removed : int
        Crossing pairs (without an ``ignored`` face) the flips removed.
    made2 : (m,) bool
        ``made`` after the flips: exact on the ``flippable`` faces (a face of ``made`` that is
        not ``flippable`` keeps its mark where its pairs are not known to have gone).
    """
    V = np.asarray(V, np.float64)
    F = np.array(F, np.int64).reshape(-1, 3)
    flippable = np.asarray(flippable, bool)
    ignored = np.zeros(len(F), bool) if ignored is None else np.asarray(ignored, bool)
    made = np.asarray(made, bool)
    # the faces within `rings` rings of the made ones may flip, and those within `reach` of them
    # (what they may cross, every face on their corners) are all a flip is tested against
    A = vertex_adjacency(F, len(V)).tocsr()
    ring = np.zeros(len(V))
    ring[F[made & flippable].ravel()] = 1.0
    for _ in range(rings):
        ring = np.maximum(ring, (A @ ring > 0).astype(np.float64))
    core = (ring[F] > 0).any(axis=1)
    window = np.flatnonzero(near_faces(V, F, core, reach))
    W = F[window]
    can = flippable[window] & core[window]
    skip = ignored[window]
    angles = triangle_min_angles(V, F[flippable])  # of all flippable faces, updated in place
    slot = np.full(len(F), -1)
    slot[flippable] = np.arange(len(angles))
    slot = slot[window]
    flipped = np.zeros(len(W), bool)
    removed = 0
    pad = 1e-8 * float(np.ptp(V, axis=0).max() or 1.0)

    def crossing(faces, extra=None):
        return _window_crossings(V, W, skip, reach, faces, extra)

    def candidates(work):
        return _flip_candidates(V, W, can, work)

    work = made[window] & can
    todo = work.copy()  # the work faces whose candidates may have changed since last tested
    for _ in range(passes):
        # every candidate of the pass is tested at once, against the surface as the pass found it
        at_work = np.zeros(len(V), bool)
        at_work[W[todo].ravel()] = True
        pairs = crossing(np.flatnonzero(can & at_work[W].any(axis=1)))  # every face a candidate changes
        count = np.bincount(pairs.ravel(), minlength=len(W))
        cands = [c for c in candidates(todo) if count[c[0]] + count[c[1]] > 0]
        if not cands:
            break
        after = _new_pair_crossings(V, W, skip, reach, [c[2] for c in cands])
        gain = np.array([count[f] + count[g] for f, g, _ in cands]) - after
        angle = np.array([triangle_min_angles(V, new).min() for _, _, new in cands])
        boxes = []  # the quads flipped in this pass: a flip beside one was tested without it
        stood = False
        for c in np.lexsort((-angle, -gain)):
            f, g, new = cands[c]
            if gain[c] <= 0:
                break
            box = _quad_box(V, new, boxes)
            if box is None:
                continue
            old = angles[slot[[f, g]]].copy()
            angles[slot[[f, g]]] = triangle_min_angles(V, new)
            if float(np.percentile(angles, 5)) < floor:
                angles[slot[[f, g]]] = old
                continue
            W[[f, g]] = new
            flipped[[f, g]] = work[[f, g]] = True
            boxes.append(box)
            removed += int(gain[c])
            stood = True
        if not stood:
            break
        # a candidate's test looks at the faces whose boxes meet its quad's: only those beside a
        # flip of this pass can come out differently
        lo, hi = V[W].min(axis=1), V[W].max(axis=1)
        beside = np.zeros(len(W), bool)
        for qlo, qhi in boxes:
            beside |= np.all((lo <= qhi + pad) & (hi >= qlo - pad), axis=1)
        todo = work & beside
    F[window] = W
    out = np.zeros(len(F), bool)
    out[window[flipped]] = True
    made2 = made & ~core  # their pairs with no face of the core are as they were
    made2[window[crossing(np.flatnonzero(core[window])).ravel()]] = True
    return F, out, removed, made2


def flip_for_angles(V, F, flippable, *, floor, reach, ignored=None, passes=ANGLE_FLIP_PASSES,
                    max_bend=ANGLE_FLIP_BEND):
    """Edge flips that raise the smallest angles of the ``flippable`` faces whose minimum angle is
    under ``floor``: the slivers the cut and the repair leave where the remesher cannot reach
    (:func:`.remesh.flip_to_improve_angles` flips the remeshed junction before any repair,
    blind to what it crosses).

    An edge of such a face shared with another ``flippable`` face is a candidate where its flip
    (:func:`_flip_candidates`: the other diagonal of the two faces' quad) raises the pair's
    smaller minimum angle, the quad is nearly flat (its two faces' normals within ``max_bend``
    degrees of each other, before and after: the surface keeps its shape) and the two new faces
    cross no more faces than the old two (pairs with an ``ignored`` face aside). A pass tests
    every candidate at once against the surface as the pass found it; flips then stand in order
    of the larger minimum angle, where their quad meets no quad flipped in the same pass. Passes
    repeat while one stands, at most ``passes``. Vertices never move and the face count stays.

    Parameters
    ----------
    V : (n, 3) float array
        Positions (welded by position).
    F : (m, 3) int array
    flippable : (m,) bool
        Faces whose connectivity may change (generated junction faces in no crossing pair).
    floor : float
        Degrees: the faces under it are worked on.
    reach : float
        Faces within about this distance of a flipped quad are tested for crossings (same unit
        as ``V``).
    ignored : (m,) bool, optional
        Faces whose crossing pairs do not count.

    Returns
    -------
    F2 : (m, 3) int64
        ``F`` with the flipped faces rewritten in place (same count, same order).
    flipped : (m,) bool
        Faces whose corners changed.
    """
    V = np.asarray(V, np.float64)
    F = np.array(F, np.int64).reshape(-1, 3)
    flippable = np.asarray(flippable, bool)
    flipped_all = np.zeros(len(F), bool)
    angles = triangle_min_angles(V, F)
    bad = flippable & (angles < floor)
    if not bad.any():
        return F, flipped_all
    # the slivers, the faces across their edges, and what those may cross
    A = vertex_adjacency(F, len(V)).tocsr()
    at = np.zeros(len(V))
    at[F[bad].ravel()] = 1.0
    core = ((A @ at > 0) | (at > 0))[F].any(axis=1)
    window = np.flatnonzero(near_faces(V, F, core, reach))
    W = F[window]
    can = flippable[window]
    skip = np.zeros(len(W), bool) if ignored is None else np.asarray(ignored, bool)[window]
    a = angles[window]
    flipped = np.zeros(len(W), bool)
    cos_bend = np.cos(np.radians(max_bend))
    for _ in range(passes):
        cands = []  # (f, g, new, the new pair's smaller minimum angle)
        for f, g, new in _flip_candidates(V, W, can, can & (a < floor)):
            n_old, n_new = _face_normals(V[W[[f, g]]]), _face_normals(V[new])
            angle = triangle_min_angles(V, new).min()
            if angle - min(a[f], a[g]) > 1e-6 and n_old[0] @ n_old[1] >= cos_bend and n_new[0] @ n_new[1] >= cos_bend:
                cands.append((f, g, new, angle))
        if not cands:
            break
        changed = np.zeros(len(W), bool)
        for f, g, _, _ in cands:
            changed[[f, g]] = True
        count = np.bincount(_window_crossings(V, W, skip, reach, np.flatnonzero(changed)).ravel(),
                            minlength=len(W))
        after = _new_pair_crossings(V, W, skip, reach, [c[2] for c in cands])
        boxes = []
        for c in np.argsort(-np.array([c[3] for c in cands]), kind="stable"):
            f, g, new, _ = cands[c]
            if after[c] > count[f] + count[g]:
                continue
            box = _quad_box(V, new, boxes)
            if box is None:
                continue
            W[[f, g]] = new
            a[[f, g]] = triangle_min_angles(V, new)
            flipped[[f, g]] = True
            boxes.append(box)
        if not boxes:
            break
    F[window] = W
    flipped_all[window[flipped]] = True
    return F, flipped_all


@dataclass(frozen=True)
class JunctionRepair:
    """A junction surface after :func:`repair_junction`.

    Attributes
    ----------
    JV : (k, 3) float64, JF : (q, 3) int64
        The junction: its faces (its knots filled again, :func:`fan_fill`), then the released
        kept faces, over its own vertices (those it shares with kept faces at their exact
        positions).
    released : (mK,) bool
        Kept faces that joined the junction.
    found, left, layered : int
        As :class:`CrossingRepair`; ``found`` counts the pairs before any repair (knots included).
    moved : bool
        Whether anything changed (else ``JV``, ``JF`` are the input's).
    largest_move : float
        The largest distance a vertex moved (same units as the positions; 0 when none did).
    made : (mJ,) bool
        Faces of the given junction ``JF`` in a crossing left that the inputs did not have
        (:attr:`CrossingRepair.made`; a refilled knot's on the first face of its region). Where
        no knot was refilled, the first ``mJ`` faces of ``JF`` out are these, in order.
    """

    JV: np.ndarray
    JF: np.ndarray
    released: np.ndarray
    found: int
    left: int
    layered: int
    moved: bool
    made: np.ndarray
    largest_move: float = 0.0


def repair_junction(KV, KF, JV, JF, *, counted, layered=None, rounds=6, min_angle=20.0) -> JunctionRepair:
    """Repair the crossings of a junction surface with itself and the kept faces around it
    (:func:`repair_crossings` on the two welded by position, as the report counts crossings).

    Parameters
    ----------
    KV : (nK, 3) float array, KF : (mK, 3) int array
        The kept faces (copied from the inputs): they may join the junction, never move otherwise.
    JV : (nJ, 3) float array, JF : (mJ, 3) int array
        The junction; its vertices at a kept vertex's position are that vertex.
    counted : (mK,) bool
        Kept faces whose crossings count as the junction's (the report's junction faces).
    layered : callable, optional
        ``layered(faces)`` for kept faces ``faces`` (indices into ``KF``), see
        :func:`repair_crossings`.
    rounds, min_angle
        See :func:`repair_crossings`.

    Returns
    -------
    JunctionRepair
    """
    from ..geometry import weld
    from .junction import remove_unreferenced

    JV = np.asarray(JV, np.float64).reshape(-1, 3)
    JF = np.asarray(JF, np.int64).reshape(-1, 3)
    KF = np.asarray(KF, np.int64).reshape(-1, 3)
    nK, mK = len(KV), len(KF)
    unchanged = JunctionRepair(JV=JV, JF=JF, released=np.zeros(mK, bool), found=0, left=0, layered=0, moved=False,
                               made=np.zeros(len(JF), bool))
    if rounds <= 0 or len(JF) == 0:
        return unchanged
    Vw, index, Fw = weld(np.concatenate([np.asarray(KV, np.float64).reshape(-1, 3), JV]),
                         np.concatenate([KF, JF + nK]))
    movable = np.ones(len(Vw), bool)
    movable[index[:nK]] = False
    E = np.concatenate([JF[:, [0, 1]], JF[:, [1, 2]], JF[:, [2, 0]]])
    target = float(np.median(np.linalg.norm(JV[E[:, 0]] - JV[E[:, 1]], axis=1)))

    def repair(V_, F_, movable_):
        check = np.concatenate([np.asarray(counted, bool), np.ones(len(F_) - mK, bool)])
        return repair_crossings(V_, F_, movable_, check, target=target, releasable=np.arange(len(F_)) < mK,
                                layered=layered, rounds=rounds, min_angle=min_angle)

    rep = repair(Vw, Fw, movable)
    origin, knots = np.arange(len(JF)), None
    if rep.left > rep.layered:  # crossings the inputs did not have are left: are some knots?
        uE, cnt = edge_counts(Fw)
        fixed = ~movable
        fixed[uE[cnt != 2].ravel()] = True
        knots = _untie_knots(Vw, Fw, mK, fixed, min_angle)
    if knots is not None:
        Vk, Fk, origin_k = knots
        rep_k = repair(Vk, Fk, np.concatenate([movable, np.ones(len(Vk) - len(Vw), bool)]))
        if rep_k.left - rep_k.layered < rep.left - rep.layered:  # kept where it leaves fewer made pairs
            found = rep.found  # the pairs before any repair, knots included
            Vw, Fw, origin, rep = Vk, Fk, origin_k, replace(rep_k, found=found)
        else:
            knots = None
    flipped = False
    if rep.left > rep.layered:  # folds of slivers with the wrong diagonal?
        generated = np.arange(len(Fw)) >= mK
        floor = min(min_angle, float(np.percentile(triangle_min_angles(rep.V, Fw[generated]), 5)))
        F2, _, removed, made2 = flip_apart(rep.V, Fw, generated, rep.made, ignored=rep.layered_faces, reach=target,
                                           floor=floor)
        if removed:
            log.info("fusion: %d crossing face pairs at the junction removed by edge flips", removed)
            Fw, rep, flipped = F2, replace(rep, left=rep.left - removed, made=made2), True
    junction = np.arange(len(Fw)) >= mK  # the junction out: its faces and the released kept ones
    junction[:mK] = rep.released[:mK]
    if junction.any() and float(np.percentile(triangle_min_angles(rep.V, Fw[junction]), 5)) < min_angle:
        # slivers the remesher could not reach (at the cut, kept faces released, the moves' own)
        F2, changed = flip_for_angles(rep.V, Fw, junction & ~rep.made, floor=min_angle, reach=target,
                                      ignored=rep.layered_faces)
        if changed.any():
            log.info("fusion: %d junction faces flipped to larger angles", int(changed.sum()))
            Fw, flipped = F2, True
    made = np.zeros(len(JF), bool)
    made[origin[rep.made[mK:]]] = True  # on the given junction's faces, a refilled knot's on its first
    counts = {"found": rep.found, "left": rep.left, "layered": rep.layered, "made": made}
    if rep.steps == 0 and knots is None and not flipped:
        return JunctionRepair(JV=JV, JF=JF, released=np.zeros(mK, bool), moved=False, **counts)
    faces = np.concatenate([np.arange(mK, len(Fw)), np.flatnonzero(rep.released)])
    JV2, JF2, _ = remove_unreferenced(rep.V, Fw[faces])
    largest = float(np.linalg.norm(rep.V - Vw, axis=1).max()) if len(Vw) else 0.0
    return JunctionRepair(JV=JV2, JF=JF2, released=rep.released[:mK], moved=True, largest_move=largest, **counts)
