"""Bone-to-bone mappings B_0, B_1, ...: every input joint -> an output joint with a confidence
(PIPELINE.md section 2; SkinMixer sec. 5).

Initialization (confidence 1): joints copied into the output skeleton S_R and fused pairs.
Propagation: while some input joint ``b_i`` is unmapped and has a mapped neighbour ``b'_i`` in
its own skeleton, take the pair whose neighbour has the highest confidence, score every
candidate ``b_j`` of S_R, pick the best (score + injectivity bonus) and set
``c(b_i) = c(b'_i) * score(b_j)`` (the bonus ranks, it never enters the confidence).

Scores (all parts in [0, 1], so a score is in [0, 1]):

``"paper"`` (default), weights :data:`PAPER_WEIGHTS`:
    geometric 0.3 (mean of the local-direction and root-relative-direction cosines, clipped at
    0), topological 0.3 (``1/k``, ``k`` = hops in S_R between ``b_j`` and ``B(b'_i)``, ``k = 2``
    when they are equal, 0 when unreachable), parametric 0.3 (``1 - |P_i - P_j|``, ``P`` = mean
    over the root-to-leaf paths through a joint of its normalized arc length along the path),
    valence 0.1 (min/max of the child counts, 1 when both are 0). Candidates: every joint of S_R.
``"prototype"`` (the public prototype), weights :data:`PROTOTYPE_WEIGHTS`:
    path 0.35 (``1 - (0.05 |dA|/A_max + 0.95 |dP|)``, ``A`` = arc length from the root,
    ``A_max`` the longest root-to-leaf path of both skeletons), topology 0.3, relative (local)
    direction 0.15, global (root-relative) direction 0.1, children-count ratio 0.1.
    Candidates: ancestors and descendants of ``B(b'_i)`` (itself included).

Injectivity bonus ``(0.5, 0.1)``: +0.5 for a candidate that no joint of this input maps to yet,
+0.1 for one picked only with confidence < 1.

Input and output directions are compared in the same space: the input joints are taken from the
positioned characters (scaled and moved onto S_R, :class:`rigmix.operations.Plan.positioned`).
Input joints not reachable from any mapped joint (none in practice: roots are linked to each
other) keep target ``-1`` and confidence 0.
"""

from __future__ import annotations

import heapq
import logging
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import shortest_path

__all__ = [
    "BoneMap",
    "PAPER_WEIGHTS",
    "PROTOTYPE_WEIGHTS",
    "INJECTIVITY_BONUS",
    "SkeletonFeatures",
    "skeleton_features",
    "hop_distances",
    "HopRows",
    "paper_score",
    "prototype_score",
    "propagate",
    "map_bones",
]

logger = logging.getLogger(__name__)

#: Weights of the paper's score: geometric, topological, parametric position, valence.
PAPER_WEIGHTS = {"geometric": 0.3, "topological": 0.3, "parametric": 0.3, "valence": 0.1}
#: Weights of the prototype's score.
PROTOTYPE_WEIGHTS = {"path": 0.35, "topology": 0.3, "relative_direction": 0.15,
                     "global_direction": 0.1, "children": 0.1}
#: Ranking bonus: (not picked yet, picked only with confidence < 1).
INJECTIVITY_BONUS = (0.5, 0.1)


@dataclass(frozen=True)
class BoneMap:
    """The mapping of one input skeleton onto the output skeleton.

    Attributes
    ----------
    source : str
        Character id in the config.
    target : (J_in,) int64
        Output joint of each input joint, ``-1`` when unmapped.
    confidence : (J_in,) float64
        In [0, 1]; 1 for joints copied into the output and for fused joints.
    """

    source: str
    target: np.ndarray
    confidence: np.ndarray

    def __post_init__(self):
        t = np.array(self.target, dtype=np.int64, copy=True)
        c = np.array(self.confidence, dtype=np.float64, copy=True)
        if t.shape != c.shape or t.ndim != 1:
            raise ValueError(f"BoneMap {self.source!r}: target {t.shape} and confidence {c.shape} differ")
        t.setflags(write=False)
        c.setflags(write=False)
        object.__setattr__(self, "target", t)
        object.__setattr__(self, "confidence", c)

    def matrix(self, num_output_joints: int) -> np.ndarray:
        """``(J_in, J_R)`` 0/1 matrix: ``W_in @ B`` re-indexes weights onto the output joints."""
        B = np.zeros((len(self.target), num_output_joints))
        ok = self.target >= 0
        B[np.flatnonzero(ok), self.target[ok]] = 1.0
        return B


@dataclass(frozen=True)
class SkeletonFeatures:
    """Per-joint quantities the scores compare (all arrays ``(J, ...)``).

    Attributes
    ----------
    parents : (J,) int64
    local_dir : (J, 3) float64
        Unit direction from the parent to the joint; for a secondary root (a forest's other
        trees: IK targets, props), from the main root (the largest tree's); 0 for the main root.
    root_dir : (J, 3) float64
        Unit direction from the joint's root to the joint; the same as ``local_dir`` for roots.
    param : (J,) float64
        Parametric position P in [0, 1] (0 at roots, 1 at leaves).
    arc : (J,) float64
        Arc length from the root along the bones.
    max_path : float
        Longest root-to-leaf arc length.
    children : (J,) int64
        Number of children.
    """

    parents: np.ndarray
    local_dir: np.ndarray
    root_dir: np.ndarray
    param: np.ndarray
    arc: np.ndarray
    max_path: float
    children: np.ndarray


def _unit(v):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.where(n > 1e-12, n, 1.0), 0.0)


def skeleton_features(parents, positions) -> SkeletonFeatures:
    """Directions, parametric positions and valences of a skeleton.

    Parameters
    ----------
    parents : (J,) int array
        Topological order (``parents[j] < j``), ``-1`` for roots.
    positions : (J, 3) float array
        Joint rest positions, world space.

    Returns
    -------
    SkeletonFeatures
    """
    parents = np.asarray(parents, dtype=np.int64)
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    J = len(parents)
    root = np.arange(J)
    arc = np.zeros(J)
    for j in range(J):
        p = parents[j]
        if p >= 0:
            root[j] = root[p]
            arc[j] = arc[p] + np.linalg.norm(P[j] - P[p])
    # A forest's trees are linked through their roots (``propagate``): a secondary root (an IK
    # target, a prop) takes its directions from the main root (the largest tree's), otherwise
    # every secondary root has zero directions and the left and right IK roots tie.
    size = np.bincount(root, minlength=J)
    main = int(np.argmax(size)) if J else 0
    anchor = np.where(parents >= 0, np.maximum(parents, 0), main)
    local_dir = _unit(P - P[anchor])
    root_dir = np.where((parents >= 0)[:, None], _unit(P - P[root]), local_dir)
    children = np.bincount(parents[parents >= 0], minlength=J).astype(np.int64)
    # P_j: mean over the leaves of j's subtree of arc[j] / arc[leaf]
    total = np.zeros(J)
    count = np.zeros(J)
    for leaf in np.flatnonzero(children == 0):
        j = leaf
        L = arc[leaf]
        while j >= 0:
            total[j] += arc[j] / L if L > 1e-12 else (1.0 if j == leaf else 0.0)
            count[j] += 1
            j = parents[j]
    param = np.where(count > 0, total / np.maximum(count, 1), 0.0)
    return SkeletonFeatures(parents, local_dir, root_dir, param, arc,
                            float(arc.max()) if J else 0.0, children)


def _bone_graph(parents):
    """The skeleton's bones as a ``(J, J)`` CSR adjacency (child -> parent)."""
    parents = np.asarray(parents, dtype=np.int64)
    J = len(parents)
    c = np.flatnonzero(parents >= 0)
    return coo_matrix((np.ones(len(c)), (c, parents[c])), shape=(J, J)).tocsr()  # Floyd-Warshall (small J) needs csr


def hop_distances(parents) -> np.ndarray:
    """All-pairs hop counts on the skeleton tree, ``(J, J)`` float64, ``inf`` across trees."""
    return shortest_path(_bone_graph(parents), directed=False, unweighted=True)


class HopRows:
    """Rows of :func:`hop_distances` on demand: memory ``O(J)`` a row instead of ``(J, J)``.

    ``rows[j]`` is the ``(J,)`` float64 row of hop counts from joint ``j`` (the same values as
    ``hop_distances(parents)[j]``). Propagation asks for the rows of neighbouring joints one
    after the other, so a row is derived from its parent's or a child's row when that one is
    kept (one hop more or less, by which side of the bone a joint lies on: the subtree is a
    range of the depth-first order), else found by a breadth-first search. The last
    :attr:`CACHED` rows asked for are kept.
    """

    #: Rows kept (160 KiB each on a 20,000-joint skeleton).
    CACHED = 64

    def __init__(self, parents):
        self.parents = np.asarray(parents, dtype=np.int64)
        self.graph = _bone_graph(self.parents)
        self.rows = {}
        J = len(self.parents)
        children = [[] for _ in range(J)]
        for k in np.flatnonzero(self.parents >= 0):
            children[self.parents[k]].append(int(k))
        order, stack = [], [int(r) for r in np.flatnonzero(self.parents < 0)[::-1]]
        while stack:  # preorder: each subtree is a contiguous range
            k = stack.pop()
            order.append(k)
            stack.extend(reversed(children[k]))
        self.first = np.zeros(J, np.int64)
        self.first[order] = np.arange(len(order))
        self.size = np.ones(J, np.int64)
        for k in reversed(order):
            if self.parents[k] >= 0:
                self.size[self.parents[k]] += self.size[k]

    def _subtree(self, j) -> np.ndarray:
        """``(J,)`` bool: joint ``j`` and its descendants."""
        return (self.first >= self.first[j]) & (self.first < self.first[j] + self.size[j])

    def _derived(self, j):
        """Row ``j`` from a kept row one bone away, or None."""
        p = int(self.parents[j])
        if p >= 0 and p in self.rows:  # from the parent: one hop less into j's subtree, one more elsewhere
            d = self.rows[p]
            return np.where(self._subtree(j), d - 1.0, d + 1.0)
        for c, d in self.rows.items():
            if self.parents[c] == j:  # from a child: one hop more into its subtree, one less elsewhere
                return np.where(self._subtree(c), d + 1.0, d - 1.0)
        return None

    def __getitem__(self, j) -> np.ndarray:
        j = int(j)
        row = self.rows.pop(j, None)
        if row is None:
            row = self._derived(j)
            if row is None:
                row = shortest_path(self.graph, directed=False, unweighted=True, indices=j)
            if len(self.rows) >= self.CACHED:
                self.rows.pop(next(iter(self.rows)))
        self.rows[j] = row  # most recent last
        return row


def _cos(u, V):
    """``max(0, cos)`` between a unit vector ``u`` (3,) and rows of ``V`` (n, 3); 1 if both zero."""
    d = V @ u
    uz = not np.any(u)
    vz = (V[:, 0] == 0) & (V[:, 1] == 0) & (V[:, 2] == 0)  # ~np.any(V, axis=1), without a reduce per row
    out = np.clip(d, 0.0, 1.0)
    out = np.where(vz & uz, 1.0, out)
    return out


def _ratio(a, b):
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    hi = np.maximum(a, b)
    return np.where(hi > 0, np.minimum(a, b) / np.where(hi > 0, hi, 1.0), 1.0)


def _topological(hops):
    k = np.where(hops == 0, 2.0, hops)
    return np.where(np.isfinite(k), 1.0 / k, 0.0)


def paper_score(fin, i, fout, hops_from_image, *, weights=PAPER_WEIGHTS):
    """The paper's score of every output joint as the image of input joint ``i``.

    Parameters
    ----------
    fin, fout : SkeletonFeatures
        Of the input skeleton (positioned) and of S_R.
    i : int
        The input joint being mapped.
    hops_from_image : (J_R,) float array
        Hops in S_R from ``B(b'_i)`` (the image of the mapped neighbour) to every joint.

    Returns
    -------
    score : (J_R,) float64 in [0, 1]
    """
    g = 0.5 * (_cos(fin.local_dir[i], fout.local_dir) + _cos(fin.root_dir[i], fout.root_dir))
    t = _topological(hops_from_image)
    p = 1.0 - np.abs(fin.param[i] - fout.param)
    v = _ratio(fin.children[i], fout.children)
    return (weights["geometric"] * g + weights["topological"] * t + weights["parametric"] * p
            + weights["valence"] * v)


def prototype_score(fin, i, fout, hops_from_image, *, weights=PROTOTYPE_WEIGHTS):
    """The prototype's score (see the module docstring); same parameters as :func:`paper_score`."""
    amax = max(fin.max_path, fout.max_path, 1e-12)
    path = 1.0 - (0.05 * np.abs(fin.arc[i] - fout.arc) / amax + 0.95 * np.abs(fin.param[i] - fout.param))
    t = _topological(hops_from_image)
    return (weights["path"] * np.clip(path, 0.0, 1.0) + weights["topology"] * t
            + weights["relative_direction"] * _cos(fin.local_dir[i], fout.local_dir)
            + weights["global_direction"] * _cos(fin.root_dir[i], fout.root_dir)
            + weights["children"] * _ratio(fin.children[i], fout.children))


def _ancestors_or_descendants(parents, b):
    """``(J,)`` bool: ``b``, its ancestors and its descendants."""
    J = len(parents)
    mask = np.zeros(J, dtype=bool)
    mask[b] = True
    for k in range(b + 1, J):  # topological order: descendants in one pass
        if parents[k] >= 0 and mask[parents[k]]:
            mask[k] = True
    j = parents[b]
    while j >= 0:
        mask[j] = True
        j = parents[j]
    return mask


def propagate(parents_in, positions_in, init_target, parents_out, positions_out, *,
              score="paper", injectivity_bonus=INJECTIVITY_BONUS, weights=None):
    """Complete a partial joint mapping by propagation over the input skeleton.

    Parameters
    ----------
    parents_in : (J_in,) int array
    positions_in : (J_in, 3) float array
        Input joint rest positions, in the output's space (after positioning).
    init_target : (J_in,) int array
        Output joint of the joints known with confidence 1, ``-1`` for the others.
    parents_out : (J_R,) int array
    positions_out : (J_R, 3) float array
    score : {"paper", "prototype"}
    injectivity_bonus : (float, float)
        Added to the ranking of a candidate not picked yet / picked only with confidence < 1.
    weights : dict, optional
        Score weights (default :data:`PAPER_WEIGHTS` or :data:`PROTOTYPE_WEIGHTS`).

    Returns
    -------
    target : (J_in,) int64
        ``-1`` where no mapped joint is reachable.
    confidence : (J_in,) float64 in [0, 1]
    """
    if score not in ("paper", "prototype"):
        raise ValueError(f"mapping: unknown score {score!r}, expected 'paper' or 'prototype'")
    fn = paper_score if score == "paper" else prototype_score
    w = weights or (PAPER_WEIGHTS if score == "paper" else PROTOTYPE_WEIGHTS)
    parents_in = np.asarray(parents_in, dtype=np.int64)
    parents_out = np.asarray(parents_out, dtype=np.int64)
    fin = skeleton_features(parents_in, positions_in)
    fout = skeleton_features(parents_out, positions_out)
    hops = HopRows(parents_out)  # the rows propagation asks for: a (J_R, J_R) matrix is 3.2 GB at 20,000 joints
    J, JR = len(parents_in), len(parents_out)
    target = np.asarray(init_target, dtype=np.int64).copy()
    conf = np.where(target >= 0, 1.0, 0.0)
    picked = np.full(JR, -1.0)  # best confidence with which each output joint is picked
    for t, c in zip(target[target >= 0], conf[target >= 0]):
        picked[t] = max(picked[t], c)

    nbrs = [[] for _ in range(J)]
    for j in range(J):
        p = parents_in[j]
        if p >= 0:
            nbrs[j].append(p)
            nbrs[p].append(j)
    roots = np.flatnonzero(parents_in < 0)
    for r in roots:  # roots are linked to each other (a forest is one graph)
        nbrs[r].extend(int(x) for x in roots if x != r)

    heap = []
    for j in np.flatnonzero(target >= 0):
        for k in nbrs[j]:
            if target[k] < 0:
                heapq.heappush(heap, (-conf[j], k, j))
    b_new, b_low = injectivity_bonus
    while heap:
        negc, i, nb = heapq.heappop(heap)
        if target[i] >= 0:
            continue
        image = target[nb]
        s = fn(fin, i, fout, hops[image], weights=w)
        rank = s + np.where(picked < 0, b_new, np.where(picked < 1.0, b_low, 0.0))
        if score == "prototype":
            rank = np.where(_ancestors_or_descendants(parents_out, image), rank, -np.inf)
        best = int(np.argmax(rank))
        target[i] = best
        conf[i] = float(np.clip(-negc * s[best], 0.0, 1.0))
        picked[best] = max(picked[best], conf[i])
        for k in nbrs[i]:
            if target[k] < 0:
                heapq.heappush(heap, (-conf[i], k, i))
    return target, conf


def map_bones(plan, *, score="paper", injectivity_bonus=INJECTIVITY_BONUS, weights=None):
    """B_i for every input character of a plan.

    Parameters
    ----------
    plan : rigmix.operations.Plan
    score : {"paper", "prototype"}
    injectivity_bonus : (float, float)
    weights : dict, optional
        Override the score weights.

    Returns
    -------
    dict of str -> BoneMap
        By character id, in the config's order.
    """
    out_pos = plan.skeleton.rest_worlds()[:, :3, 3]
    maps = {}
    for cid, ch in plan.positioned.items():
        pos = ch.skeleton.rest_worlds()[:, :3, 3]
        target, conf = propagate(ch.skeleton.parents, pos, plan.image[cid], plan.skeleton.parents, out_pos,
                                 score=score, injectivity_bonus=injectivity_bonus, weights=weights)
        maps[cid] = BoneMap(cid, target, conf)
        logger.debug("mapping: %s: %d joints mapped by propagation, min confidence %.3f",
                     cid, int(np.sum(plan.image[cid] < 0)), float(conf.min()) if len(conf) else 1.0)
    return {cid: maps[cid] for cid in plan.image if cid in maps}
