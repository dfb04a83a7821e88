"""Quality figures that need no ground truth (PIPELINE.md section 7).

Junction stretch ratio
----------------------
Per face, the deformation gradient from rest to a posed frame is
``G = [e1' e2' n'] [e1 e2 n]^-1`` (two edges and the unit normal, rest and posed); its stretch
part (polar decomposition ``G = R U``) has the singular values ``s`` of ``G``, and the face's
stretch is ``||log s||`` (0 for a rigid motion). A vertex's stretch is the rest-area-weighted
mean over its faces. The figure of a band is the 95th percentile over its surface and over
every frame (30 fps, at most ``max_frames`` per clip, evenly spaced) of every clip: each vertex
counts for a third of the rest area of its faces (:func:`vertex_areas`), so that a densely
tessellated rigid piece (a head of thousands of vertices) weighs what its area does, in the
input's band and in the output's alike, and a part replaced by a coarser one does not change
the percentile by its vertex count.

Bands. On the output: the vertices within ``r`` of a fused joint (rest pose), where ``r`` is the
reach of the junction (the largest distance from a junction vertex to its nearest fused joint),
and at least the distance to the nearest vertex (a mesh coarser than the junction). On the
sources: each input's own vertices within ``r / scale`` of its joint of that fused pair
(``scale`` the input's scale in the composition), at least the nearest one, over the input's
own clips; an input without clips (it moves only as completion animates it) by its own
vertices in the output band, which keep its weights, under the output's clips. Each input's
figure is taken over its band alone, and the ratio is the output figure over the largest of
them: about 1 when the seam deforms like the more supple of the parts it joins, whatever their
vertex counts (a tiny rigid wing scaled onto a body must not outweigh the body around it).

Junction weight roughness
-------------------------
A weight spike (a vertex whose weights differ from all its neighbours') deforms one vertex
apart from the surface around it; the 95th percentile of the stretch does not see one vertex.
A vertex's roughness is half the L1 distance between its weights and the mean of its
neighbours' weights, on the mesh welded by position (0: the mean of its neighbours; 1: no
joint in common with any of them). The junction figure is taken over the junction vertices
of the fused surface; the sources' over every vertex of the fusion's inputs, the artists'
own painting, where the sharpest painted transitions reach 0.6 to 0.8 (the shared characters).

Grafted part visibility
-----------------------
A grafted part can end up buried in the other body (a torso scaled down into a chest, a part
left behind by a ``replace`` around the new one): every figure above passes and the output looks
like the body alone. :func:`grafted_visibility` measures, for each grafted input (role
``source`` in the plan: it only gives subtrees), the share of the area of its output faces whose
generalized winding number with respect to the kept surface of every other input (the faces the
output copies from it) is below 0.5: outside them (the inputs' faces oriented outwards, as glTF
front faces are; near a single-sided sheet of another input the front side reads outside, the
back side inside). At rest, on the fused surface. A grafted input's output faces
(:func:`face_owners`) are those copied from it and the generated junction faces that follow its
surface most: a low-poly limb rebuilt whole by the fusion keeps a surface. The other input's
generated junction faces hide nothing: the junction is open where it meets the part, and the
winding number of an open surface closes it across that opening, so beside a junction that
narrows from the body's hole to a thinner part (a funnel) the part's own surface would read
inside a surface it lies outside of. Each face is sampled at the centroids of its four midpoint
sub-triangles (a quarter of its area each).

Artists sink parts of a character into others (a leg's top into a shell, a neck into a collar),
so a part does not show whole even in its own character: the same share is taken of the faces
the output copies from the grafted input, against the rest of that input (``_source``), and the
figure held to the bound is the output's share over it, at most 1 (``_relative``). An identity
composition measures 1 whatever its character hides.

The figure sees what is in the output only: a part of the graft that the fusion swallowed (a
union or blend whose surface follows the other body there) leaves no face to measure; a graft
swallowed whole measures 0.

Junction dihedral angles
------------------------
A ragged seam shows as creases between neighbouring junction faces. :func:`junction_dihedral`
gives the 95th percentile of the angle between the normals of two junction faces that share an
edge (the faces ``junction_min_angle_p05`` measures: generated, or kept by the fusion's fallback,
not copied; the mesh welded by position), and
the same figure on the fusion's inputs (positioned, at rest) over the faces within the junction
band radius of their joint of a fused pair (the radius and centres of the stretch ratio's
bands). Their ratio is about 1 when the seam is as smooth as the artists' own surface there.

Identity errors
---------------
A composition that replaces subtrees of one character by the same subtrees of the same file
must give that character back. :func:`identity_errors` measures it on the files themselves
(the output as read back): the rest surfaces of the skinned meshes, both ways (each output
vertex to the input surface and each input vertex to the output surface), and every frame of
every output clip (30 fps), where an output vertex skinned by the output's weights and clip is
compared with the input point it was copied from, skinned by the input's weights and the clip
it was completed from: an input vertex at its rest position (the closest of them over the clip,
as glTF splits vertices at seams, :func:`identity_origins`), or else the closest input surface
point at rest. Both are relative to the input's rest bounding-box
diagonal. :func:`self_composition_errors` measures the weight stage of a self-composition
against a truth on the fused surface instead (before anything is written).
"""

from __future__ import annotations

import logging

import numpy as np

from dfd.mesh import face_areas, welded_graph

from .animation.sampling import clip_times, sample_clip
from .fusion.meshutil import dihedral_angles
from .geometry import bounding_box_diagonal, check_transforms, closest_surface_points
from .skinning import (
    linear_blend_skinning,
    rest_skinning_matrices,
    skinning_columns,
    skinning_matrices,
    skinning_operator,
)
from .sparse_weights import dense_rows

__all__ = ["face_stretch", "vertex_stretch", "clip_skinning_matrices", "band_stretch", "merged_band",
           "vertex_areas", "weighted_percentile",
           "junction_band_radius", "junction_stretch_ratio", "weight_roughness", "junction_weight_roughness",
           "outside_area_share",
           "face_owners", "grafted_visibility", "junction_dihedral", "self_composition_truth",
           "self_composition_errors", "skinned_surface", "identity_errors", "identity_origins"]

log = logging.getLogger(__name__)

#: Floats per temporary of the stretch sampling (edge vectors of the band's faces over a chunk of
#: frames): about 1 MB each. Temporaries of 32 MB are above glibc's largest mmap threshold: each
#: was mapped afresh and page-faulted in, twice the time of the whole stage on a first call.
_STRETCH_CHUNK = 1 << 17


def face_stretch(V0, U, F):
    """``||log s||`` per face, ``s`` the singular values of the rest-to-posed deformation gradient.

    The gradient ``G = [e1' e2' n'] [e1 e2 n]^-1`` maps the unit normal to the unit normal, so
    its singular values are 1 and the square roots of the eigenvalues of ``g0^-1 g1`` (the
    2 x 2 first fundamental forms of the rest and posed triangle): computed in closed form.

    Parameters
    ----------
    V0 : (n, 3) float array
        Rest positions.
    U : (k, n, 3) float array
        Posed positions, ``k`` frames.
    F : (m, 3) int array

    Returns
    -------
    (k, m) float64
        Degenerate rest faces get 0.
    """
    def forms(P):
        e1 = P[..., F[:, 1], :] - P[..., F[:, 0], :]
        e2 = P[..., F[:, 2], :] - P[..., F[:, 0], :]
        return (np.einsum("...i,...i->...", e1, e1), np.einsum("...i,...i->...", e1, e2),
                np.einsum("...i,...i->...", e2, e2))

    F = np.asarray(F, np.int64)
    return _stretch_from_forms(forms(np.asarray(V0, np.float64)), forms(np.asarray(U, np.float64)))


def _stretch_from_forms(rest, posed):
    """``||log s||`` from the first fundamental forms ``(a, b, c)`` (``e1.e1``, ``e1.e2``,
    ``e2.e2``) of the rest and posed triangles, any broadcastable shapes (see
    :func:`face_stretch`); degenerate rest triangles get 0."""
    a0, b0, c0 = rest
    a1, b1, c1 = posed
    det0 = a0 * c0 - b0 * b0
    ok = det0 > 1e-12 * np.maximum(a0 * c0, 1e-300)
    # M = g0^-1 g1; eigenvalues from its trace and determinant
    inv = np.where(ok, 1.0 / np.where(ok, det0, 1.0), 0.0)
    tr = (c0 * a1 - 2.0 * b0 * b1 + a0 * c1) * inv
    det = (a1 * c1 - b1 * b1) * inv
    disc = np.sqrt(np.maximum(tr * tr / 4.0 - det, 0.0))
    l1 = np.maximum(tr / 2.0 + disc, 1e-24)
    l2 = np.maximum(tr / 2.0 - disc, 1e-24)
    return np.where(ok, 0.5 * np.sqrt(np.log(l1) ** 2 + np.log(l2) ** 2), 0.0)


def vertex_areas(V, F, vertices):
    """A third of the area of the faces around each of ``vertices`` ``(q,)``: the share of
    the surface each vertex stands for (units of ``V`` squared; a face counts once per corner
    among them, as in :func:`band_stretch`'s means; 0 for a vertex on no face)."""
    F = np.asarray(F, np.int64).reshape(-1, 3)
    vertices = np.asarray(vertices, np.int64)
    mark = np.zeros(len(V), bool)
    mark[vertices] = True
    around = F[mark[F].any(axis=1)]  # only the faces the band touches (the output is the whole surface)
    per_vertex = np.zeros(len(V))
    np.add.at(per_vertex, around.ravel(), np.repeat(face_areas(np.asarray(V, np.float64), around) / 3.0, 3))
    return per_vertex[vertices]


def weighted_percentile(x, w, q) -> float:
    """The ``q``-th percentile (0 to 100) of samples ``x`` ``(s,)`` weighted by ``w`` ``(s,)``
    (non-negative): the smallest sample whose cumulative weight reaches ``q`` % of the total;
    the unweighted percentile where the weights sum to 0."""
    x, w = np.asarray(x, np.float64).ravel(), np.asarray(w, np.float64).ravel()
    total = float(w.sum())
    if total <= 0:
        return float(np.percentile(x, q))
    order = np.argsort(x, kind="stable")
    cum = np.cumsum(w[order])
    k = min(int(np.searchsorted(cum, q / 100.0 * total, side="left")), len(x) - 1)
    return float(x[order][k])


def _vertex_means(V0, F, vertices):
    """The rest-area-weighted mean over the faces around each of ``vertices`` ``(q,)``, as a
    matrix: ``(faces, A)``, ``faces`` ``(mb,)`` the faces of ``F`` with a corner among
    ``vertices``, ``A`` ``(q, mb)`` sparse with rows summing to 1 (a face counts once per
    corner it has among them)."""
    import scipy.sparse as sp

    F = np.asarray(F, np.int64)
    vertices = np.asarray(vertices, np.int64)
    pos = np.full(len(V0), -1)
    pos[vertices] = np.arange(len(vertices))
    faces = np.flatnonzero((pos[F] >= 0).any(axis=1))
    Fb = F[faces]
    area = face_areas(V0, Fb)
    rows, cols = pos[Fb].T.ravel(), np.tile(np.arange(len(Fb)), 3)
    sel = rows >= 0
    A = sp.csr_matrix((np.tile(area, 3)[sel], (rows[sel], cols[sel])), shape=(len(vertices), len(Fb)))
    den = np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1e-30)
    return faces, sp.diags(1.0 / den) @ A


def vertex_stretch(V0, U, F, vertices):
    """Rest-area-weighted mean face stretch at ``vertices`` ``(q,)``: returns ``(k, q)``."""
    faces, A = _vertex_means(V0, F, vertices)
    s = face_stretch(V0, U, np.asarray(F, np.int64)[faces])  # (k, mb)
    return (A @ s.T).T


def _frames(clip, fps, max_frames):
    t = clip_times(clip, fps)
    if len(t) > max_frames:
        t = t[np.round(np.linspace(0, len(t) - 1, max_frames)).astype(int)]
    return t


def clip_skinning_matrices(skeleton, clips, *, fps=30.0, max_frames=30) -> list:
    """Skinning matrices of each clip at its stretch frames (at most ``max_frames``, evenly
    spread over its samples at ``fps``): one ``(k, J, 4, 4)`` array per clip, column vectors.

    The frames of all clips go through forward kinematics together (one pass over the joints,
    not one per clip; each frame's matrices are the same floats either way)."""
    poses = [sample_clip(skeleton, clip, _frames(clip, fps, max_frames)) for clip in clips]
    if not poses:
        return []
    T, R, S = (np.concatenate([p[i] for p in poses]) for i in range(3))
    M = skinning_matrices(skeleton, T, R, S)
    return np.split(M, np.cumsum([len(p[0]) for p in poses])[:-1])


def band_stretch(skeleton, clips, V0, joints, weights, F, vertices, *, rest=None, fps=30.0, max_frames=30,
                 matrices=None):
    """Stretch samples ``(sum_clips frames x q,)`` of the band ``vertices`` of one skinned mesh.

    ``V0`` are bind-space positions; ``rest`` the rest-pose positions the gradient starts from
    (default: ``V0`` skinned by the rest pose). ``matrices``: the clips' skinning matrices
    (:func:`clip_skinning_matrices`) when the caller has them already (several meshes or bands
    under the same clips); sampled here otherwise.
    """
    if len(vertices) == 0 or not clips:
        return np.zeros(0)
    F = np.asarray(F, np.int64)
    mark = np.zeros(len(V0), bool)
    mark[np.asarray(vertices, np.int64)] = True
    # only the faces around the band matter: skin their vertices alone
    sub = np.unique(F[mark[F].any(axis=1)].ravel())
    pos = np.full(len(V0), -1)
    pos[sub] = np.arange(len(sub))
    Fs = pos[F[(pos[F] >= 0).all(axis=1)]]
    V0s, Js, Ws = np.asarray(V0)[sub], np.asarray(joints)[sub], np.asarray(weights)[sub]
    if rest is None:
        rest = linear_blend_skinning(V0s, Js, Ws, rest_skinning_matrices(skeleton))
    else:
        rest = np.asarray(rest)[sub]
    vs = pos[np.asarray(vertices, np.int64)]
    if matrices is None:
        matrices = clip_skinning_matrices(skeleton, clips, fps=fps, max_frames=max_frames)
    M = np.concatenate([np.asarray(m, np.float64) for m in matrices])  # (k, J, 4, 4), the clips' frames
    faces, A = _vertex_means(rest, Fs, vs)
    Fb = Fs[faces]
    if not len(Fb):  # vertices on no face: 0, as the mean over no face
        return np.zeros(len(M) * len(vs))
    # the posed edge vectors are linear in the skinning matrices: no posed positions needed
    B = skinning_operator(V0s, Js, Ws, M.shape[1])
    E1, E2 = (B[Fb[:, 1]] - B[Fb[:, 0]]).tocsr(), (B[Fb[:, 2]] - B[Fb[:, 0]]).tocsr()
    r1, r2 = rest[Fb[:, 1]] - rest[Fb[:, 0]], rest[Fb[:, 2]] - rest[Fb[:, 0]]
    rest_forms = tuple(np.einsum("mi,mi->m", x, y)[:, None] for x, y in ((r1, r1), (r1, r2), (r2, r2)))
    out = []
    step = max(1, _STRETCH_CHUNK // (3 * len(Fb)))
    for start in range(0, len(M), step):
        C = skinning_columns(M[start:start + step])
        e1 = (E1 @ C).reshape(len(Fb), -1, 3)
        e2 = (E2 @ C).reshape(len(Fb), -1, 3)
        posed = (np.einsum("mki,mki->mk", e1, e1), np.einsum("mki,mki->mk", e1, e2),
                 np.einsum("mki,mki->mk", e2, e2))
        out.append((A @ _stretch_from_forms(rest_forms, posed)).T)  # (frames, q)
    return np.concatenate(out).ravel()


def merged_band(parts):
    """Skinned meshes and their band vertices as one mesh, for :func:`band_stretch`.

    ``parts``: ``(mesh, rest, vertices)`` per mesh (a :class:`rigmix.character.Mesh`, its rest
    positions ``(n_i, 3)``, its band vertices ``(q_i,)``). Returns ``(V0, joints, weights, F,
    vertices, rest)`` over the meshes' vertices in order (faces and band vertices offset, the
    influences padded with zero weights to the widest): no face joins two meshes, so each
    vertex's mean and each face's stretch are those of its own mesh.
    """
    if not parts:
        return (np.zeros((0, 3)), np.zeros((0, 1), np.int64), np.zeros((0, 1)), np.zeros((0, 3), np.int64),
                np.zeros(0, np.int64), np.zeros((0, 3)))
    width = max(np.asarray(m.joints).reshape(len(m.positions), -1).shape[1] for m, _, _ in parts)

    def padded(a, n, dtype):
        a = np.asarray(a, dtype).reshape(n, -1)
        return np.pad(a, ((0, 0), (0, width - a.shape[1])))

    offsets = np.cumsum([0] + [len(m.positions) for m, _, _ in parts])
    return (np.concatenate([np.asarray(m.positions, np.float64) for m, _, _ in parts]),
            np.concatenate([padded(m.joints, len(m.positions), np.int64) for m, _, _ in parts]),
            np.concatenate([padded(m.weights, len(m.positions), np.float64) for m, _, _ in parts]),
            np.concatenate([np.asarray(m.faces, np.int64) + o for (m, _, _), o in zip(parts, offsets)]),
            np.concatenate([np.asarray(b, np.int64) + o for (_, _, b), o in zip(parts, offsets)]),
            np.concatenate([np.asarray(x, np.float64) for _, x, _ in parts]))


def junction_band_radius(V, junction_vertices, centres) -> float:
    """Reach of the junction: the largest distance from a junction vertex to its nearest centre.

    Parameters
    ----------
    V : (n, 3) float array
        Fused surface, rest pose (metres, composed world).
    junction_vertices : (n,) bool array
    centres : (k, 3) float array
        Rest positions of the fused joints, ``k >= 1``.

    Returns
    -------
    float
        Same unit as ``V``; a tenth of the bounding-box diagonal of ``V`` without junction vertices.
    """
    V = np.asarray(V, np.float64)
    jv = np.flatnonzero(junction_vertices)
    if not len(jv):
        return 0.1 * float(np.linalg.norm(np.ptp(V, axis=0)))
    return float(np.linalg.norm(V[jv, None, :] - np.asarray(centres)[None], axis=2).min(axis=1).max())


def junction_stretch_ratio(composition, *, fps=30.0, max_frames=30, percentile=95.0) -> dict:
    """The junction stretch ratio of a composition (see the module docstring).

    Parameters
    ----------
    composition : rigmix.pipeline.Composition
        After the assembly stage (``character`` with its clips) and the fusion.

    Returns
    -------
    dict
        ``junction_stretch_ratio`` (None without clips or fused joints), ``output_p95``,
        ``source_p95`` (the largest input figure), ``source_p95_by_input`` (input id -> figure),
        ``band_radius``, ``output_band_vertices``, ``source_band_vertices``.
    """
    from .weights import to_influences

    plan = composition.plan
    surface = composition.surface
    skin = composition.weights
    ch = composition.character
    V = np.asarray(surface.V)
    out = {"junction_stretch_ratio": None, "output_p95": None, "source_p95": None, "band_radius": None,
           "output_band_vertices": 0, "source_band_vertices": 0, "source_p95_by_input": {}}
    pairs = plan.junction_pairs
    if not pairs or ch is None or not ch.clips:
        return out
    Jpos = plan.skeleton.rest_worlds()[:, :3, 3]
    P = Jpos[[p.output for p in pairs]]  # (k, 3)
    r = junction_band_radius(V, surface.junction_vertices, P)
    to_joints = np.linalg.norm(V[:, None, :] - P[None], axis=2).min(axis=1)
    r = max(r, float(to_joints.min()))  # a coarse mesh: the band holds at least the nearest vertex
    band = np.flatnonzero(to_joints <= r)
    J, W = to_influences(skin.W, 4)
    # each skeleton's clips are sampled once, whatever the number of bands and meshes under them
    matrices = {None: clip_skinning_matrices(ch.skeleton, ch.clips, fps=fps, max_frames=max_frames)}
    s_out = band_stretch(ch.skeleton, ch.clips, V, J, W, surface.F, band, rest=V, matrices=matrices[None])
    a_out = _sample_areas(V, surface.F, band, s_out)
    samples, nsrc = {}, 0  # per input: (stretch samples, their areas) of its band, under its own clips
    bands = {}  # (input, joint, reach) -> its band's samples: a character composed with itself is sampled once
    rests_of = {}  # input -> rest positions of its skinned meshes
    for p in pairs:
        for cid, j in ((p.target, p.target_joint), (p.source, p.source_joint)):
            src = composition.inputs[cid]
            meshes = [m for m in src.meshes if m.skinned and len(m.faces) and len(m.positions)]
            if not src.clips or not meshes:
                continue
            if id(src) not in matrices:
                matrices[id(src)] = clip_skinning_matrices(src.skeleton, src.clips, fps=fps, max_frames=max_frames)
                M0 = rest_skinning_matrices(src.skeleton)
                rests_of[id(src)] = [linear_blend_skinning(m.positions, m.joints, m.weights, M0) for m in meshes]
            rests = rests_of[id(src)]
            scale = float(plan.scales.get(cid, 1.0)) or 1.0
            c = src.skeleton.rest_worlds()[j, :3, 3]
            dists = [np.linalg.norm(x - c, axis=1) for x in rests]
            # the input's band, at least its nearest vertex (not each mesh's: a prop or a far
            # part of a modular character has no vertex near the joint)
            reach = max(r / scale, min(float(d.min()) for d in dists))
            key = (id(src), j, reach)
            if key not in bands:
                inside = [np.flatnonzero(d <= reach) for d in dists]
                # the meshes with band vertices as one (each face and vertex sampled as on its own)
                V0, joints, weights, faces, vertices, rest = merged_band(
                    [(m, x, b) for m, x, b in zip(meshes, rests, inside) if len(b)])
                measured = []
                if len(vertices):
                    stretch = band_stretch(src.skeleton, src.clips, V0, joints, weights, faces, vertices, rest=rest,
                                           matrices=matrices[id(src)])
                    measured.append((stretch, _sample_areas(rest, faces, vertices, stretch)))
                bands[key] = (measured, sum(len(b) for b in inside))
            band_samples, count = bands[key]
            nsrc += count
            samples.setdefault(cid, []).extend(band_samples)
    # an input without clips moves only as completion animates it: its figure is that of its
    # own vertices in the output band, which keep its weights, under the output's clips
    for cid in dict.fromkeys(c for p in pairs for c in (p.target, p.source)):
        if composition.inputs[cid].clips or cid not in composition.fusion_ids:
            continue
        own = band[(surface.origin_input[band] == composition.fusion_ids.index(cid))
                   & ~np.asarray(surface.junction_vertices)[band]]
        nsrc += len(own)
        stretch = band_stretch(ch.skeleton, ch.clips, V, J, W, surface.F, own, rest=V, matrices=matrices[None])
        samples.setdefault(cid, []).append((stretch, _sample_areas(V, surface.F, own, stretch)))
    figures = {cid: weighted_percentile(np.concatenate([s for s, _ in x]), np.concatenate([a for _, a in x]),
                                        percentile)
               for cid, x in samples.items() if sum(len(s) for s, _ in x)}
    out.update(band_radius=r, output_band_vertices=int(len(band)), source_band_vertices=int(nsrc),
               source_p95_by_input=figures)
    if len(s_out) and figures:
        a, b = weighted_percentile(s_out, a_out, percentile), max(figures.values())
        out.update(output_p95=a, source_p95=b, junction_stretch_ratio=a / max(b, 1e-12))
    return out


def _sample_areas(V, F, vertices, stretch):
    """The area each of :func:`band_stretch`'s samples ``stretch`` (frame-major over
    ``vertices``) stands for: its vertex's, once per frame."""
    per_vertex = vertex_areas(V, F, vertices)
    return np.tile(per_vertex, len(stretch) // max(len(per_vertex), 1))


def weight_roughness(V, F, W, rows=None):
    """Half the L1 distance from each vertex's weights to the mean of its neighbours'.

    Parameters
    ----------
    V : (n, 3) float array
        Split vertices (welded by position here: the split copies of a seam are one vertex).
    F : (m, 3) int array
    W : (n, J) float array or scipy.sparse matrix
        Rows summing to 1 (sparse: the same figures, with memory in the influences).
    rows : (n,) bool array, optional
        The vertices to measure (a welded vertex is measured when any of its copies is);
        default all.

    Returns
    -------
    (k,) float64
        One value per measured welded vertex with at least one neighbour, in ``[0, 1]``.
    """
    import scipy.sparse as sp

    from .geometry import neighbour_roughness

    W = W.tocsr() if sp.issparse(W) else np.asarray(W, np.float64)
    # the 0/1 adjacency: no lengths, and no sort of the edges, most of the cost at a million faces
    Vw, index, A = welded_graph(V, F, lengths=False)
    k = len(Vw)
    copies = np.bincount(index, minlength=k)
    Ww = sp.csr_matrix((1.0 / copies[index], (index, np.arange(len(index)))), shape=(k, len(index))) @ W
    r, measured = neighbour_roughness(A, Ww)
    if rows is not None:
        selected = np.zeros(k, bool)
        selected[index[np.asarray(rows, bool)]] = True
        measured &= selected
    return r[measured]


def junction_weight_roughness(composition) -> dict:
    """Weight roughness of the junction and of the fusion's inputs (see the module docstring).

    Parameters
    ----------
    composition : rigmix.pipeline.Composition
        After the weights stage (``surface``, ``weights``,
        ``fusion_inputs``).

    Returns
    -------
    dict
        ``junction_weight_roughness_p99`` / ``_max`` (None without junction vertices) and
        ``source_weight_roughness_p99`` / ``_max``.
    """
    surface = composition.surface
    W = composition.weights.W
    junction = np.asarray(surface.junction_vertices, bool)
    r = weight_roughness(surface.V, surface.F, W, junction) if junction.any() else np.zeros(0)
    src = [weight_roughness(x.V, x.F, x.W) for x in composition.fusion_inputs if len(x.F)]
    src = np.concatenate(src) if src else np.zeros(0)

    def figures(x):
        return (float(np.percentile(x, 99.0)), float(x.max())) if len(x) else (None, None)

    (junction_p99, junction_max), (source_p99, source_max) = figures(r), figures(src)
    return {"junction_weight_roughness_p99": junction_p99, "junction_weight_roughness_max": junction_max,
            "source_weight_roughness_p99": source_p99, "source_weight_roughness_max": source_max}


#: Barycentric coordinates of the centroids of a triangle's four midpoint sub-triangles: each
#: stands for a quarter of the triangle's area.
_SUBTRIANGLE_CENTROIDS = np.array([[4.0, 1.0, 1.0], [1.0, 4.0, 1.0], [1.0, 1.0, 4.0], [2.0, 2.0, 2.0]]) / 6.0


def outside_area_share(V, F, occluders):
    """Share of the area of a surface outside every occluder (generalized winding number below 0.5).

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        The surface measured.
    occluders : sequence of ((p, 3) float array, (q, 3) int array)
        Surfaces, open or closed, oriented outwards, in the same space as ``V``; a point is
        inside one when its generalized winding number (``igl.fast_winding_number``, triangle
        soup) with respect to it is at least 0.5.

    Returns
    -------
    float or None
        In ``[0, 1]``: the area of ``F`` whose sample points (the centroids of each face's four
        midpoint sub-triangles, a quarter of its area each) are inside no occluder, over the area
        of ``F``; 1 without occluders; None when ``F`` has no area.
    """
    import igl

    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    area = face_areas(V, F)
    total = float(area.sum())
    if total <= 0:
        return None
    Q = np.einsum("sk,mkc->msc", _SUBTRIANGLE_CENTROIDS, V[F]).reshape(-1, 3)  # (4 m, 3), face-major
    outside = np.ones(len(Q), bool)
    for Vo, Fo in occluders:
        Fo = np.asarray(Fo, np.int64).reshape(-1, 3)
        if not len(Fo):
            continue
        used, Fc = np.unique(Fo, return_inverse=True)  # only the occluder's own vertices
        Vc = np.ascontiguousarray(np.asarray(Vo, np.float64)[used])
        w = igl.fast_winding_number(Vc, np.ascontiguousarray(Fc.reshape(-1, 3)), Q[outside])
        keep = np.flatnonzero(outside)
        outside[keep[w >= 0.5]] = False
    visible = outside.reshape(-1, 4).mean(axis=1)
    # the same pairwise sum as ``total``: a surface wholly visible gives exactly 1 (a BLAS dot
    # rounds differently from it, and by thread count)
    return float(min((area * visible).sum() / total, 1.0))


def face_owners(surface, *, near=1e-3):
    """The input whose surface each output face belongs to.

    A face copied from an input (``face_origin_input >= 0``) belongs to it. A generated junction
    face belongs to the input its corners follow most: the largest sum over its three corners of
    ``presence / (distance + near * diagonal)`` at each input's closest point
    (:attr:`rigmix.fusion.FusedSurface.junction_sources`), the weighting the fusion gives the
    junction's colours. A grafted part the fusion rebuilt whole (a low-poly limb with no face
    preserved) is then still its own.

    Parameters
    ----------
    surface : rigmix.fusion.FusedSurface
    near : float
        Distances under about this fraction of the surface's bounding-box diagonal count as on the
        input's surface.

    Returns
    -------
    (M,) int64
        Input index per face of ``surface.F``; -1 only for a generated face of a surface without
        inputs.
    """
    F = np.asarray(surface.F, np.int64).reshape(-1, 3)
    owner = np.asarray(surface.face_origin_input, np.int64).copy()
    generated = np.flatnonzero(owner < 0)
    sources = surface.junction_sources
    if not len(generated) or not len(sources):
        return owner
    eps = near * max(bounding_box_diagonal(surface.V), 1e-300)
    rows = np.flatnonzero(surface.junction_vertices)  # the rows of junction_sources
    corners = F[generated]  # (g, 3)
    k = np.clip(np.searchsorted(rows, corners), 0, max(len(rows) - 1, 0))
    sourced = rows[k] == corners if len(rows) else np.zeros(corners.shape, bool)
    origin = np.asarray(surface.origin_input)[corners]
    score = np.zeros((len(generated), len(sources)))
    for i, src in enumerate(sources):
        w = np.asarray(src["presence"])[k] / (np.asarray(src["distance"])[k] + eps) if len(rows) else 0.0
        # a corner the weights stage copies is its own input's vertex: on that surface, fully present
        score[:, i] = np.where(sourced, w, np.where(origin == i, 1.0 / eps, 0.0)).sum(axis=1)
    owner[generated] = np.argmax(score, axis=1)
    return owner


def _held_by_others(x, V, F) -> bool:
    """Whether every face of input ``x`` (positions as given) is a face of the output ``(V, F)``."""
    def keys(P, T):
        C = np.sort(np.asarray(P, np.float64)[np.asarray(T, np.int64)].reshape(len(T), 3, 3), axis=1)
        return {row.tobytes() for row in C.reshape(len(T), 9)}

    return len(x.F) > 0 and keys(x.V, x.F) <= keys(V, F)


def grafted_visibility(surface, inputs, ids, roles) -> dict:
    """How much of each grafted part shows, against how much it shows in its own character
    (see the module docstring).

    Parameters
    ----------
    surface : rigmix.fusion.FusedSurface
        At rest; each face belongs to one input (:func:`face_owners`).
    inputs : sequence of rigmix.fusion.FusionInput
        The fusion's inputs, positioned (``Composition.fusion_inputs``).
    ids : sequence of str
        The character id of each fusion input (``Composition.fusion_ids``).
    roles : mapping of str -> str
        ``"body"`` or ``"source"`` per character id (``Plan.report["characters"][id]["role"]``);
        the sources are the grafted parts.

    Returns
    -------
    dict
        Per grafted input id: ``grafted_visible``, the share of the area of its output faces
        outside the other inputs' kept (copied) faces, in ``[0, 1]`` (0 when none of its surface is in
        the output: a part the union swallowed whole); ``grafted_visible_source``, the share of its
        faces copied into the output that is outside the rest of its own character (None when
        none is copied); ``grafted_visible_relative``, the first over the second, at most 1 (the
        first alone without the second). ``grafted_visible_min``: the smallest relative share
        (None without a grafted part). A part that owns no output face because the output holds
        every face it has as the other input's (faces both share: an identity composition) has no
        entry.
    """
    V = np.asarray(surface.V, np.float64)
    F = np.asarray(surface.F, np.int64)
    owner = face_owners(surface)
    origin = np.asarray(surface.face_origin_input)
    visible, source, relative = {}, {}, {}
    for i, cid in enumerate(ids):
        if roles.get(cid) != "source":
            continue
        others = [(V, F[origin == k]) for k in range(len(ids)) if k != i]
        share = outside_area_share(V, F[owner == i], others)
        if share is None and _held_by_others(inputs[i], V, F):
            continue  # its faces are those both inputs share, kept once from the other (an identity)
        visible[cid] = 0.0 if share is None else share
        # the same faces in their own character: parts an artist sank into another (a leg into a
        # shell, a neck into a collar) are hidden there too, and an identity composition must pass
        x = inputs[i]
        copied = np.zeros(len(x.F), bool)
        copied[np.asarray(surface.face_origin_face)[origin == i]] = True
        Fx = np.asarray(x.F, np.int64)
        source[cid] = outside_area_share(x.V, Fx[copied], [(x.V, Fx[~copied])])
        relative[cid] = (visible[cid] if not source[cid] else min(visible[cid] / source[cid], 1.0))
    return {"grafted_visible": visible, "grafted_visible_source": source, "grafted_visible_relative": relative,
            "grafted_visible_min": min(relative.values()) if relative else None}


def junction_dihedral(composition, *, percentile=95.0) -> dict:
    """Dihedral angles of the junction against the inputs' own (see the module docstring).

    Parameters
    ----------
    composition : rigmix.pipeline.Composition
        After the fusion stage (``surface``, ``fusion_inputs``, ``fusion_ids``, ``plan``).
    percentile : float

    Returns
    -------
    dict
        ``junction_dihedral_p95`` (degrees; None without two neighbouring junction faces that are
        not copied: a copied junction or none), ``source_dihedral_p95`` (degrees; None without a fused
        pair between fusion inputs or a band face pair), ``junction_dihedral_ratio`` (their ratio,
        None when either is None).
    """
    plan = composition.plan
    surface = composition.surface
    ids = list(composition.fusion_ids)
    rebuilt = np.asarray(surface.junction_faces, bool) & ~np.asarray(surface.copied_faces, bool)
    angles = dihedral_angles(surface.V, surface.F, rebuilt) if rebuilt.any() else np.zeros(0)
    junction = float(np.percentile(angles, percentile)) if len(angles) else None
    pairs = [p for p in plan.junction_pairs if p.target in ids and p.source in ids]
    source = None
    if pairs:
        centres = plan.skeleton.rest_worlds()[[p.output for p in pairs], :3, 3]
        r = junction_band_radius(surface.V, surface.junction_vertices, centres)
        samples = []
        for i, cid in enumerate(ids):
            joints = [j for p in pairs for c, j in ((p.target, p.target_joint), (p.source, p.source_joint)) if c == cid]
            x = composition.fusion_inputs[i]
            if not joints or not len(x.F):
                continue
            at = plan.positioned[cid].skeleton.rest_worlds()[joints, :3, 3]  # (k, 3), composed world
            near = np.linalg.norm(np.asarray(x.V)[:, None, :] - at[None], axis=2).min(axis=1) <= r
            samples.append(dihedral_angles(x.V, x.F, near[np.asarray(x.F)].all(axis=1)))
        pooled = np.concatenate(samples) if samples else np.zeros(0)
        source = float(np.percentile(pooled, percentile)) if len(pooled) else None
    ratio = junction / max(source, 1e-12) if junction is not None and source is not None else None
    return {"junction_dihedral_p95": junction, "source_dihedral_p95": source, "junction_dihedral_ratio": ratio}


def self_composition_truth(composition, *, truth_influences=4):
    """The true W_R of a self-composition: ``(n, J_out)``, rows summing to 1, over the fused surface.

    A copied input vertex's truth is its own retargeted weights; a generated junction vertex's
    is the original's barycentric interpolation at its closest original point, cut to its
    ``truth_influences`` largest and renormalized (``None``: uncut). See
    :func:`self_composition_errors`.
    """
    plan = composition.plan
    surface = composition.surface
    ids = list(composition.fusion_ids)
    inputs = composition.fusion_inputs
    original = composition.inputs[ids[0]]
    J_out = plan.skeleton.num_joints
    # original joint -> output joint (the kept copy of either id)
    t = np.full(original.skeleton.num_joints, -1)
    for cid in ids:
        img = plan.image[cid]
        t = np.where(t >= 0, t, img)
    G = np.zeros((len(surface.V), J_out))
    oi, ov = np.asarray(surface.origin_input), np.asarray(surface.origin_vertex)
    for i in range(len(ids)):
        rows = np.flatnonzero(oi == i)
        Wi = dense_rows(inputs[i].W, ov[rows])
        for j in range(Wi.shape[1]):
            if t[j] >= 0:
                G[rows, t[j]] += Wi[:, j]
    # the truth of a copied input vertex is its own weights (above), of a generated one the
    # original's at its closest point
    jrows = np.flatnonzero(surface.junction_vertices)
    gen = np.flatnonzero(oi < 0)
    if len(gen):
        s = surface.junction_sources[0]  # the whole original surface (input 0 keeps everything at rest)
        k = np.searchsorted(jrows, gen)
        T = np.asarray(inputs[0].F)[np.asarray(s["face"])[k]]
        Wc = np.einsum("qk,qkj->qj", np.asarray(s["bary"])[k], dense_rows(inputs[0].W, T))
        for j in range(Wc.shape[1]):
            if t[j] >= 0:
                G[gen, t[j]] += Wc[:, j]
    G /= np.maximum(G.sum(axis=1, keepdims=True), 1e-12)
    if truth_influences is not None and len(jrows):
        from .weights import sparsify

        G[jrows] = sparsify(G[jrows], truth_influences)
    return G


def self_composition_errors(composition, skin, *, fps=30.0, max_frames=None, truth_influences=4) -> dict:
    """Weight and skinning errors of a self-composition against the original character.

    A self-composition replaces a subtree of a character with the same subtree of the same
    character (two config ids, one file, unit scale, no placement): every output joint is a
    joint of the original, and the original weights are the ground truth everywhere
    (PIPELINE.md section 7).

    Parameters
    ----------
    composition : rigmix.pipeline.Composition
        After the fusion stage; its inputs are one character under two ids.
    skin : rigmix.weights.blend.SkinWeights
        W_R to evaluate (any method).
    fps : float
    max_frames : int, optional
        Evenly spaced frames per clip (default: every frame at ``fps``).
    truth_influences : int or None
        The truth at a new vertex interpolates three original vertices, up to 12 joints; the
        output holds 4 (glTF). With 4 (default) the truth is cut to its 4 largest weights and
        renormalized (the best the output format can hold, so every method is measured against
        a reachable target); ``None`` keeps the full interpolation (then even a perfect
        method shows the cut: up to 2% of the diagonal on the low-poly shared characters).

    Returns
    -------
    dict
        ``junction_weight_error_mean``, ``junction_weight_error_max`` (L1 over output joints, at
        junction vertices, against the original weights at the closest original point),
        ``skinned_error_max`` and ``skinned_error_mean`` (over all vertices, frames and clips,
        relative to the bounding-box diagonal; the max is the worst frame),
        ``frames``, ``junction_vertices``.
    """
    surface = composition.surface
    plan = composition.plan
    original = composition.inputs[list(composition.fusion_ids)[0]]
    src = np.array([plan.provenance[o][0][1] for o in range(plan.skeleton.num_joints)])
    G = self_composition_truth(composition, truth_influences=truth_influences)
    jrows = np.flatnonzero(surface.junction_vertices)  # measured: every row the weight stage computed
    W = dense_rows(skin.W)  # the self-composition measure: dense (V, J), a benchmark's figure
    l1 = np.abs(W[jrows] - G[jrows]).sum(axis=1) if len(jrows) else np.zeros(0)
    V = np.asarray(surface.V)
    diag = float(np.linalg.norm(np.ptp(V, axis=0)))
    sk = original.skeleton
    check_transforms(sk.rest_worlds(), sk.names, where=f"quality: character {original.name!r}",
                     what="rest world matrix", fix="give the joint a non-zero scale in the file")
    rest_inv = np.linalg.inv(sk.rest_worlds())
    D = W - G  # skinned error = sum_o D_o T_src(o) u
    worst, total, count, per_frame = 0.0, 0.0, 0, []
    for clip in original.clips:
        times = clip_times(clip, fps)
        if max_frames is not None and len(times) > max_frames:
            times = times[np.round(np.linspace(0, len(times) - 1, max_frames)).astype(int)]
        Tt, R, S = sample_clip(sk, clip, times)
        from .transforms import trs_to_matrix

        M = sk.world_matrices(trs_to_matrix(Tt, R, S)) @ rest_inv  # (F, J, 4, 4): rest world -> posed
        Mo = M[:, src]  # (F, J_out, 4, 4)
        A = np.einsum("nj,fjab->fnab", D, Mo[..., :3, :], optimize=True)  # (F, n, 3, 4)
        err = np.linalg.norm(np.einsum("fnab,nb->fna", A[..., :3], V) + A[..., 3], axis=2) / diag
        per_frame.extend(err.max(axis=1).tolist())
        worst = max(worst, float(err.max()))
        total += float(err.sum())
        count += err.size
    return {
        "junction_weight_error_mean": float(l1.mean()) if len(l1) else 0.0,
        "junction_weight_error_max": float(l1.max()) if len(l1) else 0.0,
        "skinned_error_max": worst,
        "skinned_error_mean": total / max(count, 1),
        "frames": len(per_frame),
        "junction_vertices": int(len(jrows)),
    }


#: Vertex-frames skinned at once by :func:`identity_errors` (memory: about 50 bytes each).
IDENTITY_CHUNK = 1 << 21


def skinned_surface(character):
    """The skinned meshes of a character as one surface.

    Parameters
    ----------
    character : rigmix.character.Character

    Returns
    -------
    V : (n, 3) float64
        Bind-space positions.
    F : (m, 3) int64
        Faces, indices into ``V``.
    joints, weights : (n, K) int64 and float64
        The influences, ``K`` the most slots of any mesh (unused slots joint 0, weight 0).
    """
    meshes = [m for m in character.meshes if m.skinned and len(m.positions)]
    K = max((np.asarray(m.joints).shape[1] for m in meshes), default=1)
    V, F = [np.zeros((0, 3))], [np.zeros((0, 3), np.int64)]
    J, W = [np.zeros((0, K), np.int64)], [np.zeros((0, K))]
    offset = 0
    for m in meshes:
        j, w = np.asarray(m.joints, np.int64), np.asarray(m.weights, np.float64)
        pad = K - j.shape[1]
        V.append(np.asarray(m.positions, np.float64))
        F.append(np.asarray(m.faces, np.int64).reshape(-1, 3) + offset)
        J.append(np.pad(j, ((0, 0), (0, pad))))
        W.append(np.pad(w, ((0, 0), (0, pad))))
        offset += len(m.positions)
    return np.concatenate(V), np.concatenate(F), np.concatenate(J), np.concatenate(W)


#: Input vertices this close to an output vertex at rest (relative to the diagonal) are its
#: possible origins (:func:`identity_origins`).
IDENTITY_COINCIDENT = 1e-6


def identity_origins(Ro, Ri, Fi, face, bary, *, tol):
    """The input points each output vertex of an identity composition may have been copied from.

    glTF splits a vertex at every UV or normal seam, and the copies may carry different weights;
    an output vertex reproduces one of them, not necessarily the one whose face is closest. So
    every input vertex within ``tol`` of an output vertex at rest is a candidate origin; an output
    vertex with none is compared with its closest input surface point.

    Parameters
    ----------
    Ro : (n, 3) float64
        Output vertices at rest (world space).
    Ri : (m, 3) float64
        Input vertices at rest (world space).
    Fi : (f, 3) int64
        Input faces.
    face, bary : (n,) int64 and (n, 3) float64
        Each output vertex's closest input face and barycentric coordinates on it.
    tol : float
        Distance at which an input vertex coincides with an output vertex (world units).

    Returns
    -------
    rows : (p,) int64
        The output vertex of each candidate pair (every output vertex appears at least once).
    corners : (p, 3) int64
        The input vertices each pair interpolates.
    bary : (p, 3) float64
        Their weights (a vertex candidate is ``(i, i, i)`` with weights ``(1, 0, 0)``).
    """
    from scipy.spatial import cKDTree

    near = cKDTree(Ri).query_ball_point(Ro, r=tol)
    counts = np.fromiter((len(c) for c in near), np.int64, len(Ro))
    coincident = np.concatenate([np.asarray(c, np.int64) for c in near] + [np.zeros(0, np.int64)])
    free = np.flatnonzero(counts == 0)
    rows = np.concatenate([np.repeat(np.arange(len(Ro)), counts), free])
    corners = np.concatenate([np.repeat(coincident[:, None], 3, axis=1), Fi[face[free]]])
    weights = np.zeros((len(coincident), 3))
    weights[:, 0] = 1.0
    return rows, corners, np.concatenate([weights, bary[free]])


def identity_errors(original, output, clips, *, fps=30.0) -> dict:
    """How far a composition's output is from its input, when it should be that input.

    See the module docstring (identity errors).

    Parameters
    ----------
    original : rigmix.character.Character
        The input character.
    output : rigmix.character.Character
        The output as written, read back.
    clips : sequence of (Clip, Clip)
        ``(output clip, the original's clip it was completed from)``.
    fps : float
        Frames per second at which every clip is compared (its start and end included).

    Returns
    -------
    dict
        ``surface_error`` (largest rest distance, both ways), ``skinned_error`` (largest
        distance over every vertex and frame of every clip; 0 without clips), both relative to
        the input's rest bounding-box diagonal, or None when either character has no skinned
        face; ``frames``, the frames compared.
    """
    Vi, Fi, Ji, Wi = skinned_surface(original)
    Vo, Fo, Jo, Wo = skinned_surface(output)
    out = {"surface_error": None, "skinned_error": None, "frames": 0}
    if not len(Fi) or not len(Fo):
        return out
    Ri = linear_blend_skinning(Vi, Ji, Wi, rest_skinning_matrices(original.skeleton))
    Ro = linear_blend_skinning(Vo, Jo, Wo, rest_skinning_matrices(output.skeleton))
    diag = bounding_box_diagonal(Ri) or 1.0
    d_out, face, bary = closest_surface_points(Ro, Ri, Fi)  # output vertex -> input surface
    d_in, _, _ = closest_surface_points(Ri, Ro, Fo)  # input vertex -> output surface
    out["surface_error"] = float(max(d_out.max(), d_in.max()) / diag)
    rows, corners, bary = identity_origins(Ro, Ri, Fi, face, bary, tol=IDENTITY_COINCIDENT * diag)
    used = np.unique(corners)
    local = np.searchsorted(used, corners)
    pair_worst = np.zeros(len(rows))
    frames = 0
    for clip_out, clip_in in clips:
        times = clip_times(clip_out, fps)
        step = max(1, IDENTITY_CHUNK // (len(Vo) + len(used) + len(rows)))
        for k in range(0, len(times), step):
            t = times[k:k + step]
            Uo = linear_blend_skinning(Vo, Jo, Wo, skinning_matrices(output.skeleton,
                                                                     *sample_clip(output.skeleton, clip_out, t)))
            Ui = linear_blend_skinning(Vi[used], Ji[used], Wi[used],
                                       skinning_matrices(original.skeleton,
                                                         *sample_clip(original.skeleton, clip_in, t)))
            P = np.einsum("qk,fqkc->fqc", bary, Ui[:, local])  # each pair's input point, skinned
            err = np.linalg.norm(Uo[:, rows] - P, axis=2).max(axis=0)
            np.maximum(pair_worst, err, out=pair_worst)
            frames += len(t)
    # an output vertex is as far from its input as its best origin is
    best = np.full(len(Vo), np.inf)
    np.minimum.at(best, rows, pair_worst)
    worst = float(best.max()) if frames else 0.0
    out.update(skinned_error=worst / diag, frames=frames)
    return out
