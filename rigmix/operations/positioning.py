"""Preliminary positioning and scale matching (PIPELINE.md section 1; SkinMixer sec. 4.1).

Before fusion every source character is scaled to the units of the character it is fused
with, optionally posed (rest-pose rotations per joint) and placed, then translated so that its
fused joints land on their targets. The per-joint translations of the joints that are not fused
come from Laplacian smoothing over the skeleton graph (a harmonic field: each free joint's
translation is the mean of its neighbours'), so one fused pair gives a rigid translation and
several give a smooth field. The rest mesh follows by linear blend skinning. Two departures,
where the paper's rule misplaces a part: joints kept as children (``keep_joint``) of one target
joint are brought as a group, their mean onto it, each spread out to the target's surface
(:func:`spread_to_surface`); a limb's detached part (an IK foot) moves as its limb's root does
(:func:`limb_followers`), not onto the target's foot.

A positioned character is *rebased*: its mesh positions are its rest-pose positions in world
space and its inverse bind matrices are the inverses of its rest world matrices (bind pose =
rest pose), so later stages never need the original bind space.

Scale matching (automatic, overridable in the config): for a fused pair (joint ``a`` of the
moved character X, joint ``b`` of the target Y) the scale of X is a ratio of two lengths measured
in each character's rest pose, world space, in its own units (Y already scaled):

* ``replace``: the cross-section of the cut, ``cut_section(Y, b) / cut_section(X, a)``
  (:func:`cut_section`: the radius of the ring where the replaced part and the new part pass
  into their bodies: a neck's base against a waist), so that the new part fills the hole the
  old one leaves and is not swallowed by the body around it. A part modelled as a rigid piece
  has no such ring; the ratio of the parts' sizes (:func:`part_size`: bounding-box diagonals)
  stands in for it. The ratio of the longest bone chains from the fused joints down to a leaf
  (:func:`chain_length`, the replaced limb against the new limb) is taken instead where both
  fused joints are on limbs whose bones run along them (:data:`CHAIN_KINDS` by
  :func:`rigmix.limbs.classify_limbs`: every limb but a head) and the two measures agree
  within :data:`AGREEMENT` (a factor of 2.5): then both measure the same limb, and the chain is
  the steadier measure of a limb's length. A head's or a torso's chain means something else (a
  neck's runs up into the head, a torso's out along an arm), and the two disagree where a rig's
  bones do not follow its surface: the surface's measure is kept there. Without either (a part
  driven by no vertex) the chain ratio is used alone;
* ``attach``: the median of three estimates of how the two bodies compare where the part
  hangs (:func:`attach_scale`): the depths of the joints in their bodies (:func:`thickness`,
  the target's joint against the one the part hung from), the median distances from the fused
  joints to the vertices they drive (:func:`cross_section`), and the bounding-box diagonals of
  the two rest meshes, so that the part keeps its size relative to the body it came from (a fox's
  tail on a knight is a knight-sized fox's tail) unless one estimate is far off;
* when a measure is degenerate (a leaf joint, no vertex driven by the joint), the ratio of the
  bounding-box diagonals of the two rest meshes.

With several fused pairs the scale is the geometric mean of the pair ratios.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..config import MAX_SCALE, MIN_SCALE
from ..errors import InputError
from ..geometry import check_coordinates
from ..skinning import check_rig, linear_blend_skinning
from ..sparse_weights import dense_rows, influence_matrix, row_blocks
from ..transforms import matrix_to_trs, quat_multiply, quat_to_matrix

__all__ = [
    "AGREEMENT",
    "CHAIN_KINDS",
    "limb_kind",
    "body_plan",
    "facing_turn",
    "skeleton_adjacency",
    "smooth_translations",
    "rest_world_mesh",
    "rest_world_faces",
    "thickness",
    "chain_length",
    "cross_section",
    "part_weights",
    "cut_section",
    "part_size",
    "size",
    "pair_scale",
    "attach_scale",
    "pose_worlds",
    "rebase",
    "position_character",
    "positioning_order",
    "limb_followers",
    "spread_to_surface",
    "position_inputs",
    "check_positioned",
]

logger = logging.getLogger(__name__)

#: Largest factor between a replace's chain-length ratio and its cross-section ratio for which the
#: chain's is used (:func:`pair_scale`): within it both measure the same limb. Limbs of different
#: species differ in thickness by up to about 2.4 for the same length (a fox's foreleg on a human's
#: shoulder); a torso's chain against a neck's is off by 4 to 10.
AGREEMENT = 2.5

#: Limb kinds (:data:`rigmix.limbs.KINDS`) whose bone chain runs along the part from the fused
#: joint to its tip, so that the chain's length is the part's: a replace between two of them may
#: match chain lengths (:func:`pair_scale`). Every chain leaving the trunk but a head's (whose
#: chain ends where the skull begins); ``other`` is such a chain the classifier could not name.
CHAIN_KINDS = ("arm", "leg", "tail", "wing", "other")


# --------------------------------------------------------------------------------------------
# The skeleton graph and the harmonic translation field
# --------------------------------------------------------------------------------------------


def skeleton_adjacency(parents):
    """Adjacency of the skeleton graph, with one virtual node joining the roots.

    Parameters
    ----------
    parents : (J,) int array
        Parent of each joint, ``-1`` for roots.

    Returns
    -------
    A : (J + 1, J + 1) scipy.sparse.csr_matrix
        Symmetric 0/1 adjacency; node ``J`` is the virtual node linked to every root, so that a
        forest (the Horse has five roots) is one connected graph. With a single root the virtual
        node just copies the root's value and changes nothing.
    """
    parents = np.asarray(parents, dtype=np.int64)
    J = len(parents)
    child = np.arange(J)
    par = np.where(parents >= 0, parents, J)
    rows = np.concatenate([child, par])
    cols = np.concatenate([par, child])
    A = sp.coo_matrix((np.ones(2 * J), (rows, cols)), shape=(J + 1, J + 1)).tocsr()
    A.data[:] = 1.0
    return A


def smooth_translations(parents, fixed, values):
    """Per-joint translations: fixed where assigned, harmonic (Laplacian-smoothed) elsewhere.

    Equivalent to iterating ``t_i <- mean of neighbours' t`` on the free joints to convergence,
    solved directly (sparse Cholesky-free LU on the free block).

    Parameters
    ----------
    parents : (J,) int array
        Skeleton parents, ``-1`` for roots.
    fixed : (F,) int array
        Joints whose translation is assigned.
    values : (F, 3) float array
        Their translations (world space).

    Returns
    -------
    t : (J, 3) float64
        One fixed joint gives every joint the same translation (rigid); none gives zeros.
    """
    parents = np.asarray(parents, dtype=np.int64)
    J = len(parents)
    fixed = np.asarray(fixed, dtype=np.int64).reshape(-1)
    values = np.asarray(values, dtype=np.float64).reshape(-1, 3)
    t = np.zeros((J + 1, 3))
    if len(fixed) == 0:
        return t[:J]
    t[fixed] = values
    A = skeleton_adjacency(parents)
    L = sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A
    free = np.ones(J + 1, dtype=bool)
    free[fixed] = False
    if free.any():
        L = L.tocsr()
        Lff = L[free][:, free].tocsc()
        rhs = -(L[free][:, ~free] @ t[~free])
        t[free] = spla.splu(Lff).solve(rhs)
    return t[:J]


# --------------------------------------------------------------------------------------------
# Measures for scale matching
# --------------------------------------------------------------------------------------------


def rest_world_mesh(character):
    """Rest-pose positions in world space of all skinned meshes, stacked.

    Returns
    -------
    V : (n, 3) float64
        Every mesh of ``character.meshes`` skinned at the rest pose (unskinned ones as stored).
    W : (n, J) scipy.sparse.csr_matrix, float64
        Their skin weights per influence (:func:`rigmix.sparse_weights.influence_matrix`: the
        values of :meth:`rigmix.character.Mesh.dense_weights`; empty rows for unskinned meshes).
    """
    sk = character.skeleton
    M = sk.rest_worlds() @ sk.inverse_binds
    Vs, rows, cols, vals, base = [], [], [], [], 0
    for mesh in character.meshes:
        if mesh.skinned:
            Vs.append(linear_blend_skinning(mesh.positions, mesh.joints, mesh.weights, M))
            rows.append(base + np.repeat(np.arange(len(mesh.positions)), mesh.joints.shape[1]))
            cols.append(mesh.joints.ravel())
            vals.append(mesh.weights.ravel())
        else:
            Vs.append(np.asarray(mesh.positions))
        base += len(mesh.positions)
    if not Vs:
        return np.zeros((0, 3)), influence_matrix([], [], [], (0, sk.num_joints))
    if not rows:  # no skinned mesh
        return np.concatenate(Vs), influence_matrix([], [], [], (base, sk.num_joints))
    return np.concatenate(Vs), influence_matrix(np.concatenate(rows), np.concatenate(cols), np.concatenate(vals),
                                                (base, sk.num_joints))


def rest_world_faces(character):
    """Faces of every mesh of ``character``, indexing the rows of :func:`rest_world_mesh`, ``(m, 3)`` int64."""
    Fs, base = [], 0
    for mesh in character.meshes:
        Fs.append(np.asarray(mesh.faces, np.int64).reshape(-1, 3) + base)
        base += len(mesh.positions)
    return np.concatenate(Fs) if Fs else np.zeros((0, 3), np.int64)


def thickness(V, F, position):
    """How deep a joint lies in its body: the distance from it to the closest point of the surface.

    Parameters
    ----------
    V : (n, 3) float array
        Rest positions, world space.
    F : (m, 3) int array
    position : (3,) float array
        The joint's rest world position.

    Returns
    -------
    float or None
        Same units as ``V`` (the body's half thickness where the joint sits in its middle);
        ``None`` without faces or for a joint on the surface.
    """
    from ..geometry import closest_surface_points

    if len(F) == 0:
        return None
    d, _, _ = closest_surface_points(np.asarray(position, np.float64)[None], V, F)
    r = float(d[0])
    return r if r > 1e-9 * max(size(V, V), 1e-300) else None


def chain_length(parents, positions, j):
    """Length of the longest bone chain from joint ``j`` down to a leaf of its subtree.

    Parameters
    ----------
    parents : (J,) int array
    positions : (J, 3) float array
        Joint world positions.
    j : int

    Returns
    -------
    float
        Sum of bone lengths along the longest root-to-leaf path of the subtree at ``j``
        (0 for a leaf).
    """
    parents = np.asarray(parents)
    P = np.asarray(positions, dtype=np.float64)
    down = np.zeros(len(parents))
    for k in range(len(parents) - 1, j, -1):  # children after parents: reverse order is bottom-up
        p = parents[k]
        if p >= j:
            down[p] = max(down[p], down[k] + np.linalg.norm(P[k] - P[p]))
    return float(down[j])


def cross_section(V, W, position, j, *, min_weight=0.5, min_vertices=3):
    """Local thickness of a body at joint ``j``: median distance to the vertices it drives.

    Parameters
    ----------
    V : (n, 3) float array
        Rest positions, world space.
    W : (n, J) float array or scipy.sparse matrix
        Skin weights.
    position : (3,) float array
        Joint ``j``'s rest world position.
    j : int
    min_weight : float
        A vertex counts when its weight on ``j`` is at least this.
    min_vertices : int
        Fewer counted vertices make the measure degenerate.

    Returns
    -------
    float or None
        ``None`` when degenerate.
    """
    if len(V) == 0:
        return None
    sel = (W[:, [j]].toarray().ravel() if sp.issparse(W) else np.asarray(W)[:, j]) >= min_weight
    if sel.sum() < min_vertices:
        return None
    r = float(np.median(np.linalg.norm(V[sel] - np.asarray(position), axis=1)))
    return r if r > 0 else None


def part_weights(W, subtree):
    """Share of each vertex that belongs to a joint's part: its weights on the subtree's joints, summed.

    Parameters
    ----------
    W : (n, J) float array or scipy.sparse matrix
        Skin weights (sparse: summed a dense block of rows at a time, the same floats).
    subtree : (J,) bool array
        The joints of the part (:meth:`rigmix.character.Skeleton.subtree`).

    Returns
    -------
    (n,) float64
    """
    subtree = np.asarray(subtree, bool)
    if not sp.issparse(W):
        return np.asarray(W, np.float64)[:, subtree].sum(axis=1)
    out = np.zeros(W.shape[0])
    for rows in row_blocks(W.shape[0], W.shape[1]):
        out[rows] = dense_rows(W, rows)[:, subtree].sum(axis=1)
    return out


def cut_section(V, F, W, subtree, *, min_points=12):
    """Radius of a body part at its cut: the ring where its skin passes to the rest of its body.

    The part is the region the subtree of a joint drives, the surface a ``replace`` removes or
    grafts (:func:`part_weights`: ``w``). Its cut is where ``w`` crosses 0.5 on the surface: one
    point on every edge whose ends lie on either side, linearly interpolated (a waist under a
    torso, a neck's base, a tail's root). The radius is the median distance of those points from
    their centroid.

    A part that is a rigid piece of its own (``w`` 0 or 1 on nearly every edge: a robot's leg, a
    head modelled apart from its body) has no such ring: fewer crossing edges than ``min_points``
    (a ring around the coarsest tube, a six-sided prism of triangles, crosses 12: a side and a
    diagonal per face; fewer are a detail skinned across, such as a small collar). The measure
    is then degenerate.

    Parameters
    ----------
    V : (n, 3) float array
        Rest positions, world space, in the character's own units (a ratio of two of these is a
        scale between two characters).
    F : (m, 3) int array
    W : (n, J) float array or scipy.sparse matrix
        Skin weights.
    subtree : (J,) bool array
    min_points : int

    Returns
    -------
    float or None
        Same units as ``V``; ``None`` when degenerate.
    """
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    if len(V) == 0 or len(F) == 0:
        return None
    w = part_weights(W, subtree)
    E = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
    a, b = w[E[:, 0]], w[E[:, 1]]
    cross = (a - 0.5) * (b - 0.5) < 0
    if cross.sum() < min_points:
        return None
    t = ((0.5 - a[cross]) / (b[cross] - a[cross]))[:, None]
    P = V[E[cross, 0]] + t * (V[E[cross, 1]] - V[E[cross, 0]])
    r = float(np.median(np.linalg.norm(P - P.mean(axis=0), axis=1)))
    return r if r > 0 else None


def part_size(V, W, subtree, *, min_vertices=3):
    """Bounding-box diagonal of a joint's part (the vertices :func:`part_weights` gives at least
    0.5), same units as ``V``; ``None`` with fewer than ``min_vertices``."""
    P = np.asarray(V, np.float64)[part_weights(W, subtree) >= 0.5]
    if len(P) < min_vertices:
        return None
    d = size(P, P)
    return d if d > 0 else None


def size(V, joint_positions):
    """Bounding-box diagonal of the rest mesh (of the joints when there is no mesh)."""
    P = V if len(V) else joint_positions
    if len(P) == 0:
        return 0.0
    return float(np.linalg.norm(P.max(axis=0) - P.min(axis=0)))


def body_plan(character, plans=None):
    """:func:`rigmix.limbs.classify_limbs` of ``character``, kept in ``plans`` (a dict by ``id``
    that holds the character with its plan, so that its id stays its own) when one is given."""
    from ..limbs import classify_limbs

    plans = {} if plans is None else plans
    if id(character) not in plans:
        plans[id(character)] = (character, classify_limbs(character))
    return plans[id(character)][1]


def limb_kind(character, j, plans=None) -> str | None:
    """The kind of the limb (:func:`rigmix.limbs.classify_limbs`) whose joints hold joint ``j``
    of ``character`` (its detached ones too: an IK foot); None for a joint on no limb (the trunk).

    ``plans``: body plans kept by character (:func:`body_plan`), so that a character with several
    fused pairs is classified once."""
    name = character.skeleton.names[j]
    for limb in body_plan(character, plans).limbs:
        if name == limb.root or name in limb.joints or name in limb.detached:
            return limb.kind
    return None


def pair_scale(op, target, target_joint, source, source_joint, *, eps=1e-9, plans=None):
    """Scale to apply to ``source`` so that it matches ``target`` around one fused pair (see the
    module docstring).

    Parameters
    ----------
    op : {"attach", "replace"}
    target, source : Character
        ``target`` already in its final units (positioned), ``source`` at its own scale, both
        with bind pose = rest pose (:func:`rebase`) so that equal characters measure equal.
    target_joint, source_joint : int
    plans : dict, optional
        Body plans kept by character (:func:`limb_kind`), shared by the pairs of one positioning.

    Returns
    -------
    scale : float
    method : str
        ``"cross-section"``, ``"part-size"``, ``"limb-length"`` or ``"size"`` (the fallback).
    """
    if op != "replace":
        return attach_scale(target, target_joint, source, source_joint, eps=eps)
    tw = target.skeleton.rest_worlds()[:, :3, 3]
    sw = source.skeleton.rest_worlds()[:, :3, 3]
    Vt, Wt = rest_world_mesh(target)
    Vs, Ws = rest_world_mesh(source)
    lt = chain_length(target.skeleton.parents, tw, target_joint)
    ls = chain_length(source.skeleton.parents, sw, source_joint)
    chain = lt / ls if lt > eps and ls > eps else None
    sub_t, sub_s = target.skeleton.subtree(target_joint), source.skeleton.subtree(source_joint)
    rt = cut_section(Vt, rest_world_faces(target), Wt, sub_t)
    rs = cut_section(Vs, rest_world_faces(source), Ws, sub_s)
    if rt is not None and rs is not None:
        surface, method = rt / rs, "cross-section"
    else:
        pt, ps = part_size(Vt, Wt, sub_t), part_size(Vs, Ws, sub_s)
        surface, method = (pt / ps, "part-size") if pt is not None and ps is not None else (None, "")
    if surface is not None and (chain is None or max(chain / surface, surface / chain) > AGREEMENT
                                or limb_kind(target, target_joint, plans) not in CHAIN_KINDS
                                or limb_kind(source, source_joint, plans) not in CHAIN_KINDS):
        return surface, method
    if chain is not None:
        return chain, "limb-length"
    st, ss = size(Vt, tw), size(Vs, sw)
    if st > eps and ss > eps:
        return st / ss, "size"
    return 1.0, "size"


def attach_scale(target, target_joint, source, source_joint, *, eps=1e-9):
    """Scale of ``source`` whose part at ``source_joint`` is attached to ``target`` at ``target_joint``.

    Three estimates of how the two bodies compare where the part hangs, each fooled by something
    different, and their median (a missing one stands in by the third, so that it counts twice):

    * depth: :func:`thickness` of ``target`` at its joint over that of ``source`` at the joint its
      part hangs from (``source_joint``'s parent): the part keeps its size to the body it came
      from. Fooled by inner layers (a body under clothes puts the closest surface near the joint);
    * cross-section: :func:`cross_section` at the two fused joints, the median distance to the
      vertices each drives. Fooled where a joint drives little of its body (a hip joint that only
      holds a belt) and by parts that are not round (a wing measures its length);
    * size: the bounding-box diagonals of the two rest meshes. Fooled by long parts (a sauropod's
      neck and tail).

    Parameters and units as :func:`pair_scale` (both characters at rest in world space).

    Returns
    -------
    scale : float
    method : str
        ``"depth"``, ``"cross-section"`` or ``"size"``: the estimate the median is.
    """
    tw = target.skeleton.rest_worlds()[:, :3, 3]
    sw = source.skeleton.rest_worlds()[:, :3, 3]
    Vt, Wt = rest_world_mesh(target)
    Vs, Ws = rest_world_mesh(source)
    st, ss = size(Vt, tw), size(Vs, sw)
    whole = st / ss if st > eps and ss > eps else 1.0
    parent = int(source.skeleton.parents[source_joint])
    rt = thickness(Vt, rest_world_faces(target), tw[target_joint])
    rs = thickness(Vs, rest_world_faces(source), sw[parent]) if parent >= 0 else None
    ct = cross_section(Vt, Wt, tw[target_joint], target_joint)
    cs = cross_section(Vs, Ws, sw[source_joint], source_joint)
    estimates = [(rt / rs if rt is not None and rs is not None else whole, "depth"),
                 (ct / cs if ct is not None and cs is not None else whole, "cross-section"),
                 (whole, "size")]
    estimates = [(r, m if r != whole or m == "size" else "size") for r, m in estimates]
    return sorted(estimates, key=lambda e: e[0])[1]


# --------------------------------------------------------------------------------------------
# Moving a character
# --------------------------------------------------------------------------------------------


def _translation(t):
    M = np.eye(4)
    M[:3, 3] = t
    return M


def pose_worlds(skeleton, worlds, rotations):
    """Rest world matrices after world-axis rotations of joints about their own positions.

    Parameters
    ----------
    skeleton : Skeleton
    worlds : (J, 4, 4) float array
        Rest world matrices before the rotations.
    rotations : dict of int -> (4,) float array
        Joint -> unit quaternion xyzw in world axes; applied parents first, each one rotating
        the joint and its subtree about the joint's current position.

    Returns
    -------
    (J, 4, 4) float64
    """
    out = np.array(worlds, dtype=np.float64, copy=True)
    for j in sorted(rotations):
        R = np.eye(4)
        R[:3, :3] = quat_to_matrix(np.asarray(rotations[j], dtype=np.float64))
        p = out[j, :3, 3].copy()
        M = _translation(p) @ R @ _translation(-p)
        sub = skeleton.subtree(j)
        out[sub] = M @ out[sub]
    return out


def _locals_from_worlds(skeleton, worlds):
    """Rest local TRS of a skeleton whose joints have the given world matrices."""
    base = skeleton.root_parent_worlds()
    par = np.where(skeleton.parents[:, None, None] >= 0, worlds[np.maximum(skeleton.parents, 0)], base)
    L = np.linalg.inv(par) @ worlds
    return matrix_to_trs(L)


def _move_mesh(mesh, M_old, D, J):
    """Rest-pose a mesh (``M_old``: skinning matrices of the old rest) then apply per-joint ``D``."""
    if not mesh.skinned:
        return mesh
    V0 = linear_blend_skinning(mesh.positions, mesh.joints, mesh.weights, M_old)
    V = linear_blend_skinning(V0, mesh.joints, mesh.weights, D)
    normals = None
    if mesh.normals is not None:
        # blended linear part applied to the bind normals (rigid motions: no inverse transpose)
        A = np.einsum("nk,nkij->nij", mesh.weights, (D @ M_old)[mesh.joints][:, :, :3, :3])
        N = np.einsum("nij,nj->ni", A, mesh.normals)
        n = np.linalg.norm(N, axis=1, keepdims=True)
        normals = np.where(n > 1e-12, N / np.where(n > 1e-12, n, 1.0), mesh.normals)
    return replace(mesh, positions=V, normals=normals)


def _scale_clip(clip, skeleton, s, C):
    """Clip tracks for the character scaled by ``s`` (roots also moved by ``C``)."""
    tC, qC, _ = matrix_to_trs(C)
    A = C[:3, :3]
    rotate_roots = not np.allclose(qC, [0, 0, 0, 1])
    tracks = []
    for tr in clip.tracks:
        root = skeleton.parents[tr.joint] < 0
        vals = np.array(tr.values, copy=True)
        cubic = tr.interpolation == "CUBICSPLINE"
        if tr.path == "translation":
            if root:
                vals = vals @ A.T
                if cubic:
                    vals[:, 1] += tC
                else:
                    vals += tC
            else:
                vals = vals * s
        elif tr.path == "rotation" and root and rotate_roots:
            vals = quat_multiply(qC, vals)
        tracks.append(replace(tr, values=vals))
    return replace(clip, tracks=tuple(tracks))


def rebase(character, *, atol=1e-9):
    """The same character with bind pose = rest pose: mesh positions at rest in world space.

    The skeleton's rest transforms and the clips are kept exactly; only the inverse bind
    matrices (now ``inv(rest_world)``), mesh positions and normals change. Returns
    ``character`` itself when it is already so.
    """
    sk = character.skeleton
    W = sk.rest_worlds()
    M_old = W @ sk.inverse_binds
    if np.allclose(M_old, np.eye(4), atol=atol):
        return character
    D = np.broadcast_to(np.eye(4), W.shape)
    meshes = tuple(_move_mesh(m, M_old, D, sk.num_joints) for m in character.meshes)
    return replace(character, skeleton=replace(sk, inverse_binds=np.linalg.inv(W)), meshes=meshes)


def position_character(character, *, scale=1.0, placement=None, rotations=None, translations=None):
    """Scale, place, pose and translate a character; the rest mesh follows by skinning.

    Parameters
    ----------
    character : Character
    scale : float
        Uniform scale about the world origin.
    placement : (4, 4) float array, optional
        Rigid world transform applied after the scale.
    rotations : dict of int -> (4,) float array, optional
        Rest-pose rotations, world axes, about each joint (see :func:`pose_worlds`).
    translations : (J, 3) float array, optional
        Per-joint world translations applied last (e.g. from :func:`smooth_translations`);
        the mesh moves by ``sum_k w_k t_{j_k}``.

    Returns
    -------
    Character
        Rebased: bind pose = rest pose, mesh positions in world space. Clips are rescaled
        (non-root translation keys times ``scale``; root keys moved with the placement); the
        rest-pose rotations and translations change the rest pose only. When nothing moves,
        :func:`rebase` (rest transforms and clips kept exactly).

    Notes
    -----
    Rebasing keeps animations exact when every joint's rest skinning matrix
    ``rest_world @ inverse_bind`` is the same (bind pose = rest pose up to one global transform,
    e.g. CesiumMan's Z-up node or the Quaternius x100 armature). Where an asset's bind pose
    differs per joint from its rest pose, the rest pose becomes the bind pose: on the shared
    Horse animated vertices then move by up to about 1e-4 of its size.
    """
    sk = character.skeleton
    J = sk.num_joints
    P = np.eye(4) if placement is None else np.asarray(placement, dtype=np.float64)
    rotations = rotations or {}
    t = np.zeros((J, 3)) if translations is None else np.asarray(translations, dtype=np.float64)
    if scale == 1.0 and np.allclose(P, np.eye(4)) and not rotations and not np.any(t):
        return rebase(character)
    s = float(scale)
    G = P @ np.diag([s, s, s, 1.0])
    W = sk.rest_worlds()
    W1 = G @ W @ np.diag([1.0 / s, 1.0 / s, 1.0 / s, 1.0])
    W3 = pose_worlds(sk, W1, rotations)
    W3[:, :3, 3] += t

    T, R, S = _locals_from_worlds(sk, W3)
    skeleton = replace(sk, translations=T, rotations=R, scales=S, inverse_binds=np.linalg.inv(W3))
    M_old = G @ W @ sk.inverse_binds  # bind space -> scaled and placed rest pose
    D = W3 @ np.linalg.inv(W1)  # per joint: scaled rest -> final rest
    meshes = tuple(
        _move_mesh(m, M_old, D, J) if m.skinned else replace(m, positions=m.positions @ G[:3, :3].T + G[:3, 3])
        for m in character.meshes
    )
    Sinv = np.diag([1.0 / s, 1.0 / s, 1.0 / s, 1.0])
    Sfwd = np.diag([s, s, s, 1.0])
    props = []
    for pr in character.props:
        m = replace(pr.mesh, positions=pr.mesh.positions * s)
        M = Sfwd @ pr.matrix @ Sinv if pr.joint >= 0 else G @ pr.matrix @ Sinv
        props.append(replace(pr, mesh=m, matrix=M))
    # roots: local' = inv(anchor) @ G @ anchor @ local @ S^-1, so their keys move with C
    base = sk.root_parent_worlds()
    roots = sk.roots
    C = np.linalg.inv(base[roots[0]]) @ G @ base[roots[0]] if len(roots) else G
    if len(roots) > 1 and not all(np.allclose(base[r], base[roots[0]]) for r in roots):
        logger.debug("position_character: %s roots hang from different anchors", character.name)
    clips = tuple(_scale_clip(c, sk, s, C) for c in character.clips)
    return replace(character, skeleton=skeleton, meshes=meshes, props=tuple(props), clips=clips)


# --------------------------------------------------------------------------------------------
# All the inputs of a composition
# --------------------------------------------------------------------------------------------


def _label(character, cid) -> str:
    """``character 'cid' (file name)`` for messages (:attr:`rigmix.character.Character.label`)."""
    return f"character {cid!r} ({character.label})" if character.label else f"character {cid!r}"


def check_positioned(positioned, config) -> None:
    """Refuse positioned characters whose vertices or joints are out of range together
    (:func:`rigmix.geometry.check_coordinates`): a placement or scale that pushes one character
    far beyond the size of the composition.

    Raises
    ------
    InputError
        Naming the config, the character and its placement and scale keys.
    """
    points = {}
    for cid, ch in positioned.items():
        points[f"{_label(ch, cid)} skeleton"] = ch.skeleton.rest_worlds()[:, :3, 3]
        for k, mesh in enumerate(ch.meshes):
            points[f"{_label(ch, cid)} mesh {mesh.name or k!r}"] = mesh.positions
    check_coordinates(points, where=f"operations: config {config.source}",
                      fix="bring the characters' placement translations and scales closer to the origin "
                          "and to 1 ([characters.ID] placement, scale)")


def _check_scale(s, cid, method, config):
    if not MIN_SCALE <= s <= MAX_SCALE:
        raise InputError(
            f"operations: config {config.source}: the automatic scale of character {cid!r} ({method}) is {s:.3g}, "
            f"outside [{MIN_SCALE:g}, {MAX_SCALE:g}]: the fused joints' sizes disagree; set "
            f"characters.{cid}.scale to a number")


def _placement_matrix(placement, facing=None):
    """The placement's ``(4, 4)`` matrix; ``facing`` (a ``(3, 3)`` turn from :func:`facing_turn`)
    comes first where the placement sets no rotation. None when neither moves anything."""
    if placement is None and facing is None:
        return None
    M = np.eye(4)
    if placement is not None and placement.rotation is not None:
        M[:3, :3] = quat_to_matrix(np.asarray(placement.rotation.as_quaternion(), dtype=np.float64))
    elif facing is not None:
        M[:3, :3] = facing
    if placement is not None:
        M[:3, 3] = placement.translation
    return M


def facing_turn(source_forward, target_forward):
    """Rotation ``(3, 3)`` about +Y (column vectors, ``R @ v``) that turns the horizontal
    direction ``source_forward`` onto ``target_forward`` (world space, +Y up); the identity when
    either has no horizontal part."""
    a = np.array([source_forward[0], 0.0, source_forward[2]], dtype=np.float64)
    b = np.array([target_forward[0], 0.0, target_forward[2]], dtype=np.float64)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-9 or nb < 1e-9:
        return np.eye(3)
    a, b = a / na, b / nb
    # the angle about +Y from a to b: sin from the Y component of a x b
    theta = np.arctan2(a[2] * b[0] - a[0] * b[2], float(a @ b))
    c, s = np.cos(theta), np.sin(theta)
    R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return np.where(np.abs(R) < 1e-12, 0.0, R)


def _facing(rest, moved, positioned, config, cc, plans):
    """The turn of a moved character onto the facing of the target of its first moved pair (see
    ``positioning.face``), or None.

    Only where the two mirror planes are perpendicular (a character modelled facing +X moved onto
    one facing +Z): the plane comes from the whole rig, the facing's sign only from a vote of the
    head and the feet, which a pose can tip (the Cyberpunk character votes +Z in its file's rest
    pose and -Z in its bind pose), and a wrong half turn puts a swapped arm on backwards."""
    if not moved or not config.positioning.face or (cc.placement is not None and cc.placement.rotation is not None):
        return None
    from .mirror import mirror_plane

    target = positioned[moved[0].target]
    # the classifier's own plane (BodyPlan.symmetry_axis), at a fraction of a classification's cost:
    # the rigs are classified only where the planes differ
    if mirror_plane(rest).axis == mirror_plane(target).axis:
        return None
    R = facing_turn(body_plan(rest, plans).forward, body_plan(target, plans).forward)
    return None if np.allclose(R, np.eye(3)) else R


def _kept_shifts(pairs, here, target_of):
    """Where the joints kept as children (``keep_joint``) go.

    The kept joints of the same source attached at the same target joint are brought as a group:
    one translation brings their mean onto the target joint (two wings keep their spacing about a
    chest joint), then each is spread out to the target's surface (:func:`spread_to_surface`, the
    target's rest surface skinned once per group).

    Parameters
    ----------
    pairs : sequence of ResolvedAction
        The source's grafting actions.
    here : (J, 3) float array
        The source's joints, posed and placed (world space).
    target_of : callable
        ``target_of(cid)``: the character a target id names, positioned.

    Returns
    -------
    dict of int -> ((3,) float64, (3,) float64)
        Per kept pair (action index): its group's mean, and how much farther than the group's
        translation the joint moves (zero for a joint alone at its target).
    """
    groups: dict = {}
    for a in pairs:
        if not a.fuse:
            groups.setdefault((a.target, a.target_joint), []).append(a)
    out = {}
    for (tid, tj), group in groups.items():
        joints = [a.source_joint for a in group]
        mean = here[joints].mean(axis=0)
        if len(group) < 2:
            out[group[0].index] = (mean, np.zeros(3))
            continue
        target = target_of(tid)
        V, _ = rest_world_mesh(target)
        offsets = here[joints] - mean
        spread = spread_to_surface(V, rest_world_faces(target), target.skeleton.rest_worlds()[tj, :3, 3], offsets)
        for k, a in enumerate(group):
            out[a.index] = (mean, spread[k] - offsets[k])
    return out


#: Steps per bounding-box diagonal of the target along which :func:`spread_to_surface` looks for
#: where a ray from the target joint leaves its body.
SPREAD_STEPS = 256


def spread_to_surface(V, F, centre, offsets):
    """Offsets from a joint inside a body, lengthened where they end inside it.

    Each offset keeps its direction and is lengthened to where the ray from ``centre`` along it
    first leaves the surface ``(V, F)`` (generalized winding number below 0.5), if that is
    farther: two wing roots whose spacing is narrower than the body they are put on sit on its
    sides, not inside it.

    Parameters
    ----------
    V : (n, 3) float array, F : (m, 3) int array
        The target's rest surface, world space.
    centre : (3,) float array
        The target joint.
    offsets : (k, 3) float array
        The kept joints about it (zero rows stay zero).

    Returns
    -------
    (k, 3) float64
    """
    import igl

    offsets = np.asarray(offsets, np.float64)
    r = np.linalg.norm(offsets, axis=1)
    out = offsets.copy()
    if not len(F) or not np.any(r > 0):
        return out
    V = np.ascontiguousarray(V, np.float64)
    F = np.ascontiguousarray(F, np.int64)
    diag = size(V, V)
    t = np.linspace(0.0, diag, SPREAD_STEPS + 1)[1:]
    for i in np.flatnonzero(r > 0):
        u = offsets[i] / r[i]
        w = igl.fast_winding_number(V, F, np.asarray(centre, np.float64) + t[:, None] * u)
        outside = np.flatnonzero(w < 0.5)
        if len(outside) and t[outside[0]] > r[i]:
            out[i] = u * t[outside[0]]
    return out


def limb_followers(moved, rest, plans=None) -> dict:
    """Pairs whose source joint is a detached part of a limb (:attr:`rigmix.limbs.Limb.detached`:
    an IK foot that carries the foot's skin from the armature root) whose root another pair moves.

    Such a part moves with its limb: by the limb root's translation, so that the foot stays at
    the end of its leg (brought onto the target's foot it hung apart from the leg, by a tenth to
    a fifth of the output's size where the two legs differ in length).

    Parameters
    ----------
    moved : sequence of ResolvedAction
        The fused pairs of one source moved onto other characters.
    rest : Character
        That source at rest in world space (what is classified).
    plans : dict, optional
        Body plans kept by character (:func:`body_plan`).

    Returns
    -------
    dict of int -> ResolvedAction
        Action index of the part's pair -> the pair of its limb's root (same target character).
    """
    fused = [a for a in moved if a.fuses]
    if len(fused) < 2:
        return {}
    names = rest.skeleton.names
    by_joint = {(a.target, names[a.source_joint]): a for a in fused}
    out = {}
    for limb in body_plan(rest, plans).limbs:
        for a in fused:
            root = by_joint.get((a.target, limb.root))
            if root is not None and root is not a and names[a.source_joint] in limb.detached:
                out[a.index] = root
    return out


def positioning_order(actions, config):
    """Character ids ordered so that every target is positioned before what is moved onto it.

    Raises
    ------
    InputError
        Characters moved onto each other in a loop.
    """
    ids = list(config.characters)
    deps = {cid: set() for cid in ids}
    for a in actions:
        if a.grafts and a.source != a.target:
            deps[a.source].add(a.target)
    order, done = [], set()
    while len(order) < len(ids):
        ready = [c for c in ids if c not in done and deps[c] <= done]
        if not ready:
            left = [c for c in ids if c not in done]
            raise InputError(f"config {config.source}: characters {', '.join(map(repr, left))} are each "
                             "moved onto another in a loop; one of them must stay in place (be only a target)")
        order.append(ready[0])
        done.add(ready[0])
    return order


def position_inputs(inputs, actions, config, *, body, part, rotations):
    """Scale, pose and move every input of a composition (targets first).

    Parameters
    ----------
    inputs : dict of str -> Character
    actions : tuple of rigmix.operations.ResolvedAction
    config : rigmix.config.Config
        Scales (``"auto"`` or an override), placements, ``positioning.translate``.
    body : dict of str -> bool
        Whether each character is a body (its own joints stay in place).
    part : dict of str -> (J,) int array
        ``-1`` for a body's own joints (fixed at zero translation when it also gives subtrees).
    rotations : dict of str -> dict of int -> (4,) float array
        Rest-pose rotations by joint index.

    Returns
    -------
    positioned, scales, transforms, translations, info : dicts by character id, in the config's order
        ``transforms`` holds the scale and placement of each input, ``(4, 4)`` (world -> composed
        world, before rest-pose rotations and translations); ``info`` the report entry (scale, how
        it was chosen, the pair ratios, role).
    """
    positioned, scales, transforms, translations, info = {}, {}, {}, {}, {}
    plans = {}  # body plans of the characters measured (pair_scale), by id: each classified once
    for cid in config.characters:  # built-in and mirrored characters too, and files after rest_at_bind
        check_rig(inputs[cid], where=f"operations: {_label(inputs[cid], cid)}")
    for cid in positioning_order(actions, config):
        ch = inputs[cid]
        cc = config.characters[cid]
        sk = ch.skeleton
        pairs = [a for a in actions if a.grafts and a.source == cid and not a.identity]
        moved = [a for a in pairs if a.target != cid]
        # measured at rest in world space, as the targets are: a character matched with itself
        # then measures exactly 1 and keeps its positions bit for bit (its faces are the same
        # faces, copied once: rigmix.fusion.seams.coincident_faces)
        rest = rebase(ch) if moved else None
        if cc.scale != "auto":
            s, method, ratios = float(cc.scale), "override", []
        elif moved:
            ratios = [pair_scale(a.op, positioned[a.target], a.target_joint, rest, a.source_joint, plans=plans)
                      for a in moved]
            s = float(np.exp(np.mean(np.log([r for r, _ in ratios]))))
            method = "+".join(sorted({m for _, m in ratios}))
            _check_scale(s, cid, method, config)
        else:
            s, method, ratios = 1.0, "body", []
        rot = rotations.get(cid, {})
        turn = _facing(rest, moved, positioned, config, cc, plans)
        followers = (limb_followers(moved, rest, plans)
                     if config.positioning.translate and config.positioning.detached_with_limb else {})
        placement = _placement_matrix(cc.placement, turn)
        posed = position_character(ch, scale=s, placement=placement, rotations=rot)
        t = np.zeros((sk.num_joints, 3))
        if pairs and config.positioning.translate:
            here = posed.skeleton.rest_worlds()[:, :3, 3]
            fixed, values = [], []
            if body[cid]:
                # a body keeps its own joints in place; only the subtrees it gives move
                for j in np.flatnonzero(part[cid] == -1):
                    fixed.append(int(j))
                    values.append(np.zeros(3))
            def target_of(tid):
                return positioned[tid] if tid != cid else posed

            kept = _kept_shifts(pairs, here, target_of)
            for a in pairs:
                b = followers.get(a.index, a)  # a detached part moves as its limb's root does
                goal = target_of(b.target).skeleton.rest_worlds()[b.target_joint, :3, 3]
                fixed.append(a.source_joint)
                if a.index in kept:
                    mean, shift = kept[a.index]
                    values.append(goal - mean + shift)
                else:
                    values.append(goal - here[b.source_joint])
            t = smooth_translations(sk.parents, fixed, np.asarray(values))
        positioned[cid] = position_character(ch, scale=s, placement=placement, rotations=rot, translations=t)
        scales[cid] = s
        transforms[cid] = (np.eye(4) if placement is None else placement) @ np.diag([s, s, s, 1.0])
        translations[cid] = t
        info[cid] = {
            "scale": s,
            "scale_method": method,
            "scale_ratios": [float(r) for r, _ in ratios],
            "role": "body" if body[cid] else "source",
            "facing_turn_degrees": (0.0 if turn is None
                                    else float(np.degrees(np.arctan2(turn[0, 2], turn[0, 0])))),
            "moved": bool(np.any(t)) or s != 1.0 or bool(rot) or placement is not None,
            "moved_with_limb": [sk.names[a.source_joint] for a in pairs if a.index in followers],
        }
        if method != "override" and s != 1.0:
            logger.info("positioning: %s scaled by %.4g (%s)", cid, s, method)
    check_positioned(positioned, config)
    ids = list(config.characters)  # report in the config's order
    return ({c: positioned[c] for c in ids}, {c: scales[c] for c in ids}, {c: transforms[c] for c in ids},
            {c: translations[c] for c in ids}, {c: info[c] for c in ids})
