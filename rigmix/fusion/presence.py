"""Presence values and preserved faces (PIPELINE.md section 3, first half).

Presence says how much of each input vertex survives into the output: the sum of its skin
weights on the joints the output skeleton keeps. Topology (smoothing, components, face
morphology) runs on the mesh welded by position (section 0); values are mapped back to the
split vertices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from dfd.mesh import smooth, weld

from ..sparse_weights import dense_rows, row_blocks
from .meshutil import edge_counts, face_adjacency, nondegenerate, vertex_adjacency, vertex_components

__all__ = [
    "WeldedMesh",
    "weld_mesh",
    "raw_presence",
    "smooth_presence",
    "classify_components",
    "morphological_clean",
    "Presence",
    "compute_presence",
    "kept_shells",
]


@dataclass(frozen=True)
class WeldedMesh:
    """A split mesh and its weld.

    Attributes
    ----------
    V : (k, 3) float64
        Welded positions.
    F : (m, 3) int64
        Faces over ``V`` (same order and count as the split faces; some may be degenerate).
    index : (n,) int64
        Welded vertex of each split vertex.
    """

    V: np.ndarray
    F: np.ndarray
    index: np.ndarray


def weld_mesh(V, F) -> WeldedMesh:
    """Weld a split mesh by exact position (see :func:`dfd.mesh.weld`)."""
    Vw, index, Fw = weld(V, F)
    return WeldedMesh(Vw, Fw, index)


def raw_presence(W, used):
    """Sum of each vertex's weights on the kept joints.

    Parameters
    ----------
    W : (n, J) float array or scipy.sparse matrix
        Skin weights, rows summing to 1.
    used : (J,) bool array

    Returns
    -------
    p : (n,) float64 in [0, 1]
        The same floats for a dense or a sparse ``W`` (summed over dense blocks of rows).
    """
    W = W if sp.issparse(W) else np.asarray(W, dtype=np.float64)
    used = np.asarray(used, dtype=bool)
    n, J = W.shape
    p = np.zeros(n)
    if n and J:
        for rows in row_blocks(n, J):
            p[rows] = dense_rows(W, rows)[:, used].sum(axis=1)
    return np.clip(np.nan_to_num(p), 0.0, 1.0)


def smooth_presence(p, F, *, snap=0.02, iterations=10, alpha=0.8):
    """Snap then smooth presence with the snapped vertices fixed (uniform Laplacian).

    Parameters
    ----------
    p : (k,) float array
        Raw presence on the welded vertices.
    F : (m, 3) int array
        Welded faces.
    snap : float
        Values below ``snap`` become 0, above ``1 - snap`` become 1; those stay fixed.
    iterations, alpha : int, float
        ``p <- (1 - alpha) p + alpha mean(neighbours)`` on the free vertices
        (:func:`dfd.mesh.smooth`).

    Returns
    -------
    (k,) float64 in [0, 1]
    """
    p = np.asarray(p, dtype=np.float64).copy()
    p[p < snap] = 0.0
    p[p > 1.0 - snap] = 1.0
    free = (p > 0.0) & (p < 1.0)
    if not free.any() or iterations <= 0:
        return p
    p = smooth(vertex_adjacency(F, len(p)).astype(np.float64), p, free, iterations=iterations, alpha=alpha)
    return np.clip(p, 0.0, 1.0)


def classify_components(p, F, *, max_variance=0.04, keep_largest=True):
    """Secondary components: parts with nearly constant presence, kept whole or dropped.

    Parameters
    ----------
    p : (k,) float array
        Smoothed presence on the welded vertices.
    F : (m, 3) int array
        Welded faces.
    max_variance : float
        A component whose presence variance is below this is secondary (paper: 0.04).
    keep_largest : bool
        Never treat the component with the most faces as secondary. The paper's rule alone
        drops a whole body whose kept part is small (a finger replaced: variance < 0.04), and
        takes a receiving body that keeps every joint (attach) out of the blend; the body is
        the one part that must be blended.

    Returns
    -------
    labels : (k,) int64
        Component of each welded vertex.
    decision : (c,) int8
        Per component: 1 kept whole, 0 dropped, -1 blended (not secondary).
    """
    p = np.asarray(p, dtype=np.float64)
    labels = vertex_components(F, len(p))
    c = int(labels.max()) + 1 if len(labels) else 0
    cnt = np.bincount(labels, minlength=c).astype(np.float64)
    mean = np.bincount(labels, weights=p, minlength=c) / np.maximum(cnt, 1)
    var = np.bincount(labels, weights=(p - mean[labels]) ** 2, minlength=c) / np.maximum(cnt, 1)
    decision = np.where(var < max_variance, (mean >= 0.5).astype(np.int8), np.int8(-1)).astype(np.int8)
    if keep_largest and c:
        ok = nondegenerate(F)
        fc = np.bincount(labels[np.asarray(F)[ok, 0]], minlength=c)
        decision[int(np.argmax(fc))] = -1
    return labels, decision


def morphological_clean(mask, A, *, rounds=2):
    """Opening then closing of a face set on the face adjacency.

    Parameters
    ----------
    mask : (m,) bool
    A : (m, m) sparse face adjacency (see :func:`face_adjacency`)
    rounds : int
        Erosions/dilations per operation.

    Returns
    -------
    (m,) bool
    """
    A = A.astype(np.int32)

    def dilate(x):
        return x | (A @ x.astype(np.int32) > 0)

    def erode(x):
        return x & ~(A @ (~x).astype(np.int32) > 0)

    x = np.asarray(mask, dtype=bool).copy()
    for op in [erode] * rounds + [dilate] * rounds + [dilate] * rounds + [erode] * rounds:
        x = op(x)
    return x


@dataclass(frozen=True)
class Presence:
    """Presence of one input and the faces it contributes.

    Attributes
    ----------
    welded : WeldedMesh
    p_welded : (k,) float64
        Smoothed presence per welded vertex (secondary components forced to 0 or 1).
    p : (n,) float64
        The same per split vertex.
    preserved : (m,) bool
        Faces copied unchanged into the output.
    absent : (m,) bool
        Faces with no presence at all (or in a dropped component): not in the output.
    junction : (m,) bool
        Faces neither preserved nor absent: replaced by the junction surface.
    component_decision : (c,) int8
        See :func:`classify_components`.
    secondary : (m,) bool
        Faces of secondary components (kept whole or dropped, never blended).
    """

    welded: WeldedMesh
    p_welded: np.ndarray
    p: np.ndarray
    preserved: np.ndarray
    absent: np.ndarray
    junction: np.ndarray
    component_decision: np.ndarray
    secondary: np.ndarray


def compute_presence(V, F, W, used, *, snap=0.02, iterations=10, alpha=0.8, preserve_threshold=0.999,
                     morphology_rounds=2, secondary_variance=0.04, replaced=None,
                     replaced_present=True) -> Presence:
    """Presence, secondary components and preserved faces of one input.

    Parameters
    ----------
    V : (n, 3) float array
        Split vertex positions.
    F : (m, 3) int array
    W : (n, J) float array
        Dense skin weights.
    used : (J,) bool array
        Joints kept in the output.
    replaced : (J,) bool array, optional
        Kept joints that are the fused joint of a ``replace`` whose part comes from another
        input. A secondary component (a rigid piece, kept or dropped whole) is kept when its
        presence without them is at least 0.5: a piece riding on the replaced joint (a robot's
        thigh plate, a shoulder pad) is part of what is replaced, and the other input brings its
        own; left in place, it covers the new part (a mirrored leg inside the old one's shell).
    replaced_present : bool
        Whether the skin of the ``replaced`` joints counts as present (the default). No: a
        replace takes the target's whole region of the replaced subtree away, its root joint's
        skin included, as the presence of the joints the output keeps from it defines it, and
        the other input's part takes its place (the built-in centaur keeps the quadruped's
        neck, a stump in front of the rider, when it counts).

    Returns
    -------
    Presence
    """
    wm = weld_mesh(V, F)
    k = len(wm.V)
    if not replaced_present and replaced is not None and np.any(replaced):
        raw = raw_presence(W, np.asarray(used, bool) & ~np.asarray(replaced, bool))
    else:
        raw = raw_presence(W, used)
    # a welded vertex takes the mean of its split copies (they normally agree)
    cnt = np.bincount(wm.index, minlength=k).astype(np.float64)
    pw = np.bincount(wm.index, weights=raw, minlength=k) / np.maximum(cnt, 1)
    pw = smooth_presence(pw, wm.F, snap=snap, iterations=iterations, alpha=alpha)
    labels, decision = classify_components(pw, wm.F, max_variance=secondary_variance)
    if replaced is not None and np.any(replaced) and np.any(decision >= 0):
        own = raw_presence(W, np.asarray(used, bool) & ~np.asarray(replaced, bool))
        own_w = np.bincount(wm.index, weights=own, minlength=k) / np.maximum(cnt, 1)
        c = len(decision)
        mean = np.bincount(labels, weights=own_w, minlength=c) / np.maximum(np.bincount(labels, minlength=c), 1)
        decision = np.where(decision >= 0, (mean >= 0.5).astype(np.int8), decision).astype(np.int8)
    sec = decision[labels] >= 0
    pw = np.where(sec, decision[labels].astype(np.float64), pw)

    ok = nondegenerate(wm.F)
    fp = pw[wm.F].mean(axis=1)
    fsec = sec[wm.F[:, 0]]
    raw_pres = (fp >= preserve_threshold) & ok
    A = face_adjacency(wm.F)
    pres = morphological_clean(raw_pres & ~fsec, A, rounds=morphology_rounds)
    pres = (pres | (fsec & (fp >= 0.5))) & ok
    absent = ~pres & (pw[wm.F].max(axis=1) <= 0.0)
    absent |= ~ok
    absent |= fsec & (fp < 0.5)
    junction = ~pres & ~absent
    return Presence(wm, pw, pw[wm.index], pres, absent, junction, decision, fsec)


def kept_shells(P, kept):
    """Faces of the closed parts of an input kept whole: its secondary components (a robot's
    plates, an arm band, a buckle) the output keeps, each without a boundary edge.

    Such a part is not in the fields (it is never blended), so the isosurface of the parts it
    sits on would run through it; the fusion makes the junction around it where it crosses
    (``FusionParams.shell_clearance_voxels``).

    Parameters
    ----------
    P : Presence
    kept : (m,) bool
        The input's kept welded faces.

    Returns
    -------
    (s, 3) int64
        Welded faces of ``P``, empty when there are none.
    """
    F = P.welded.F[P.secondary & kept]
    if not len(F):
        return F
    labels = vertex_components(F, len(P.welded.V))
    uE, cnt = edge_counts(F)
    open_parts = np.unique(labels[uE[cnt == 1].ravel()])
    return F[~np.isin(labels[F[:, 0]], open_parts)]
