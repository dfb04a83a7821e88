"""Borrowing the artist's weight profile from similar known parts (PIPELINE.md section 4).

Every vertex is described relative to its two nearest bones (joint-to-child segments; a leaf
joint is a point): the joints owning them (a segment's owner is its parent end, the joint that
moves it) and the *share* of their combined weight that the nearest bone's owner takes. A hidden
vertex borrows that share from the known vertices whose features (a DFD feature field evaluated on
the mesh) are closest to its own, among the parts around *other* joints: its own joints' and
their mirror images' painting is what is hidden, and copying it is the mirror prior's job. The
borrowed shares go onto the hidden vertex's own two joints. This is the prior through which a
feature field with part semantics can pay where no mirror side is painted.

Each hidden region is trusted as far as the same borrowing explains the known vertices around it
(each predicted, like the hidden ones, from other joints' parts): a field whose nearest features
are not alike parts gets no say.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .mesh import WeldedMesh

__all__ = ["bone_owners", "borrow_prior"]


def bone_owners(X, positions, parents):
    """The joints owning the two bones nearest to each point.

    Parameters
    ----------
    X : (q, 3) points.
    positions : (J, 3) rest positions of the joints; parents : (J,) parent indices (-1: root).

    Returns
    -------
    owners : (q, 2) int64
        Owner (the segment's parent joint; a leaf joint for its own point) of the nearest and the
        second nearest bone; both the same with a single bone.
    """
    P = np.asarray(positions, dtype=np.float64)
    parents = np.asarray(parents, dtype=np.int64)
    child = np.flatnonzero(parents >= 0)
    leaf = np.setdiff1d(np.arange(len(P)), parents[child])
    owner, end = np.r_[parents[child], leaf], np.r_[child, leaf]
    a, b = P[owner], P[end]
    X = np.asarray(X, dtype=np.float64)
    ab = b - a
    D = np.empty((len(X), len(a)))
    for s in range(len(a)):
        t = np.clip(((X - a[s]) @ ab[s]) / max(float(ab[s] @ ab[s]), 1e-300), 0.0, 1.0)
        D[:, s] = np.linalg.norm(X - (a[s] + t[:, None] * ab[s]), axis=1)
    # the second bone is the nearest one of another owner (a joint with several children owns several)
    first = np.argmin(D, axis=1)
    o0 = owner[first]
    D2 = np.where(owner[None, :] == o0[:, None], np.inf, D)
    o1 = np.where(np.isfinite(D2).any(axis=1), owner[np.argmin(D2, axis=1)], o0)
    return np.stack([o0, o1], axis=1).astype(np.int64)


def _shares(W, owners):
    """``(k,)`` share of the first owner in the two owners' weight, and ``(k,)`` their weight."""
    rows = np.arange(len(W))
    a, b = W[rows, owners[:, 0]], W[rows, owners[:, 1]]
    same = owners[:, 0] == owners[:, 1]
    mass = np.where(same, a, a + b)
    share = np.where(same, 1.0, a / np.maximum(a + b, 1e-12))
    return share, mass


def _pair_keys(owners, mirror):
    """``(k,)`` int64 key of each row's unordered owner pair, the same for its mirror image's pair."""
    J = int(max(owners.max(), mirror.max())) + 1
    lo, hi = owners.min(axis=1), owners.max(axis=1)
    m = np.sort(mirror[owners], axis=1)
    return np.minimum(lo * J + hi, m[:, 0] * J + m[:, 1])


def _borrow(features, share, candidates, keys, rows, neighbours):
    """Mean share ``(r,)`` of the ``neighbours`` candidates nearest in feature space to each of
    ``rows``, among candidates whose pair key differs from the row's (nan where none)."""
    out = np.full(len(rows), np.nan)
    for key in np.unique(keys[rows]):
        pool = candidates[keys[candidates] != key]
        sel = np.flatnonzero(keys[rows] == key)
        if len(pool) == 0:
            continue
        _, nb = cKDTree(features[pool]).query(features[rows[sel]], k=min(neighbours, len(pool)))
        out[sel] = share[pool[np.asarray(nb).reshape(len(sel), -1)]].mean(axis=1)
    return out


def borrow_prior(g: WeldedMesh, W, unk, features, positions, parents, mirror, *, confidence=0.5,
                 neighbours=8, coverage=0.9, ring=8, ring_scale=0.2):
    """The prior of each hidden vertex: the weight share it borrows from feature-similar known parts.

    Parameters
    ----------
    g : WeldedMesh
    W : (k, J) welded weights (hidden rows ignored); unk : (k,) bool hidden rows.
    features : (k, C) float array
        Feature of each welded vertex (a DFD feature field evaluated at ``g.V``).
    positions, parents : the skeleton's rest joint positions ``(J, 3)`` and parents ``(J,)``.
    mirror : (J,) int
        Each joint's mirror joint (itself when central): a pair's mirror image is not "other".
    confidence : float
        Largest confidence of the prior.
    neighbours : int
        Known vertices each hidden one borrows from.
    coverage : float
        A known vertex lends its share only when its two owners hold at least this much of its
        weight (its weights are a profile between its two nearest bones).
    ring, ring_scale
        Known vertices per hidden one that check the borrowing (their mean half-L1 error ``e``
        gives the region's confidence ``confidence * exp(-(e / ring_scale)^2)``).

    Returns
    -------
    P : (k, J) prior weights (hidden rows; zero elsewhere); c : (k,) confidence in [0, 1].
    """
    k, J = W.shape
    P, c = np.zeros_like(W), np.zeros(k)
    rows, known = np.flatnonzero(unk), np.flatnonzero(~unk)
    if len(rows) == 0 or len(known) == 0:
        return P, c
    features = np.asarray(features, dtype=np.float64)
    owners = bone_owners(g.V, positions, parents)
    share, mass = _shares(W, owners)
    keys = _pair_keys(owners, np.asarray(mirror, dtype=np.int64))
    candidates = known[mass[known] >= coverage]
    if len(candidates) == 0:
        return P, c

    def profile(r, s):
        out = np.zeros((len(r), J))
        np.add.at(out, (np.arange(len(r)), owners[r, 0]), s)
        np.add.at(out, (np.arange(len(r)), owners[r, 1]), 1.0 - s)
        return out

    s = _borrow(features, share, candidates, keys, rows, neighbours)
    ok = np.isfinite(s)
    P[rows[ok]] = profile(rows[ok], s[ok])
    _, region = connected_components(g.A[rows][:, rows], directed=False)
    tree = cKDTree(g.V[known])
    for r in range(region.max() + 1):
        sel = rows[(region == r) & ok]
        if len(sel) == 0:
            continue
        _, nb = tree.query(g.V[sel], k=min(ring, len(known)))
        around = np.unique(known[np.asarray(nb).ravel()])
        sr = _borrow(features, share, candidates, keys, around, neighbours)
        good = np.isfinite(sr)
        if not good.any():
            continue
        e = 0.5 * np.abs(profile(around[good], sr[good]) - W[around[good]]).sum(axis=1).mean()
        c[sel] = confidence * np.exp(-((e / ring_scale) ** 2))
    return P, c
