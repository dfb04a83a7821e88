"""``fuse_surfaces``: the new surface M_R = M'_0 + M'_1 + M_J (PIPELINE.md section 3).

Stages, each a function of :mod:`rigmix.fusion`:

1. presence per input vertex, secondary components, preserved faces (:mod:`.presence`);
2. for attach, faces of one input inside or against the present part of the other stop being
   preserved (the union must cut through them);
3. junction clusters: boxes around the faces that are neither preserved nor absent; a cluster
   whose every face two inputs share is copied as it is (:func:`.seams.coincident_faces`), and a
   face both inputs preserve (skinned to the fused joint alone) is kept once
   (:func:`.seams.shared_preserved`);
4. local signed distance fields and their blend per action (:mod:`.fields`);
5. isosurface, cut by the preserved faces, loops bridged, remeshed and smoothed
   (:mod:`.junction`, :mod:`.remesh`);
6. crossing faces repaired: junction faces that cross the surface are smoothed or pushed apart,
   kept faces in the way joining the junction (:mod:`.crossings`);
7. assembly: preserved faces copied bit-identically, junction vertices appended.

:func:`fuse_surfaces` runs them as named steps: :func:`_partition` (1 to 3),
:func:`_fuse_cluster` per junction cluster (4, 5: :func:`.stitch.junction_for_cluster`),
:func:`_repair_crossings` (6), :func:`_assemble` (7) and :func:`_surface_report`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Literal, Sequence

import numpy as np

from ..errors import InputError
from ..geometry import bounding_box_diagonal, check_coordinates
from .fields import get_backend, prepare_surface
from .meshutil import average_edge_length, edge_counts
from .params import FusionParams
from .presence import compute_presence, kept_shells
from .report import mesh_report
from .seams import (
    attach_conflicts,
    cluster_grid,
    coincident_faces,
    drop_specks,
    junction_clusters,
    local_edge_length,
    most_present_faces,
    open_notches,
    preserved_loops,
    separate_seams,
    shared_preserved,
    under_kept_shells,
    unpinch_preserved,
)
from .stitch import junction_for_cluster

log = logging.getLogger(__name__)

__all__ = ["FusionInput", "FusionAction", "FusedSurface", "fuse_surfaces"]


@dataclass(frozen=True)
class FusionInput:
    """One input character's surface contribution, after positioning (rest pose).

    Attributes
    ----------
    V : (n, 3) float64
        Split vertices of all its skinned meshes concatenated.
    F : (m, 3) int64
    W : (n, J) float64 array or scipy.sparse matrix
        Skin weights (:func:`rigmix.fusion.inputs.fusion_input` gives a CSR matrix of the
        influences: :mod:`rigmix.sparse_weights`).
    used : (J,) bool
        Joints of this character kept in the output skeleton.
    mesh_of_vertex : (n,) int64, optional
        Which source mesh (primitive) each vertex comes from.
    uvs : (n, 2) float64, optional
    normals : (n, 3) float64, optional
    colors : (n, 4) float64, optional
        Linear RGBA (textures baked to vertex colours by the caller), interpolated at the junction.
    name : str
    replaced : (J,) bool, optional
        Joints kept in the output only as the fused joint of a ``replace`` that another input's
        part takes the place of (:func:`rigmix.fusion.presence.compute_presence`: a rigid piece
        of this input riding on them goes with the replaced part).
    parents : (J,) int64, optional
        The input skeleton's parent of each joint (``-1`` for roots).
    joint_positions : (J, 3) float64, optional
        The input's joints at rest, in the same space as ``V``. With ``parents``: where a joint
        the input does not keep falls back to at the junction
        (:func:`rigmix.weights.retarget.cut_joints_to_nearest_kept`).
    """

    V: np.ndarray
    F: np.ndarray
    W: np.ndarray  # or a scipy.sparse matrix
    used: np.ndarray
    mesh_of_vertex: np.ndarray | None = None
    uvs: np.ndarray | None = None
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    name: str = ""
    replaced: np.ndarray | None = None
    parents: np.ndarray | None = None
    joint_positions: np.ndarray | None = None


@dataclass(frozen=True)
class FusionAction:
    """Inputs ``a`` and ``b`` meet: ``replace`` (presence-weighted blend) or ``attach`` (union)."""

    kind: Literal["replace", "attach"]
    a: int
    b: int


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
        Source input and split vertex of each output vertex; ``-1`` for generated junction
        vertices.
    face_origin_input, face_origin_face : (M,) int64
        Source of each face; ``-1`` for generated junction faces. Where a junction could not be
        closed by the isosurface (open sheets), the input faces kept instead keep their source
        and are marked in ``junction_faces``.
    junction_faces : (M,) bool
        Generated faces, fallback-selected faces and copied faces.
    preserved : tuple of (m_i,) bool
        Per input, its preserved faces (presence 1) copied into the output.
    presence : tuple of (n_i,) float64
        Per input, smoothed presence per split vertex.
    mesh_of_vertex : (N,) int64
        Source mesh of the preserved vertices, ``-1`` at the junction.
    uvs, normals, colors : (N, 2), (N, 3), (N, 4) float64 or None
        Copied on preserved vertices (bit-identical); junction normals from the surface, UVs 0,
        colours interpolated from the closest input points (presence-weighted).
    junction_sources : tuple of dict
        Per input, for each of the ``junction_vertices``: ``face`` (split face of the closest
        point), ``bary`` (barycentric, (k, 3)), ``distance``, ``presence`` at that point.
    fields : tuple of (name, Grid, array)
        Blended fields (only with ``FusionParams.keep_fields``).
    junction_vertices : (N,) bool
        Vertices whose weights the weights stage computes (``junction_sources`` has one row per
        such vertex, in index order): the generated junction vertices, and the vertices of
        copied faces that no preserved face of their input shares. The others copy their input's
        weights. Defaults to ``origin_input < 0``.
    copied_faces : (M,) bool
        Junction faces copied from an input because both inputs of an action have them
        (``FusionParams.copy_coincident``); positions, UVs and normals bit-identical.
    report : dict
        ``mesh`` (vertices, faces, non_manifold_edges, new_non_manifold_edges,
        junction_boundary_edges, junction_min_angle_p05 and junction_min_angle_min (degrees, over
        the junction faces that are not copied; None without any), junction_faces, copied_faces,
        unmatched_loops, junction_self_intersections, and what the repair of crossing faces did:
        junction_crossings_repaired, junction_faces_released, junction_crossings_layered,
        junction_repair_largest_move: the farthest it moved a vertex, in the surface's units),
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
    junction_vertices: np.ndarray | None = None
    copied_faces: np.ndarray | None = None

    def __post_init__(self):
        if self.junction_vertices is None:
            object.__setattr__(self, "junction_vertices", np.asarray(self.origin_input) < 0)
        if self.copied_faces is None:
            object.__setattr__(self, "copied_faces", np.zeros(len(self.F), bool))


# --------------------------------------------------------------------------------------------


def _check_inputs(inputs, actions):
    for i, x in enumerate(inputs):
        V, F, shape = np.asarray(x.V), np.asarray(x.F), np.shape(x.W)  # dense or sparse
        if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
            raise InputError(f"fusion: input {i} ({x.name!r}) needs V (n, 3) and F (m, 3)")
        if len(shape) != 2 or shape[0] != len(V) or shape[1] != len(np.asarray(x.used)):
            raise InputError(f"fusion: input {i} ({x.name!r}) weights must be (n, J) with used (J,)")
        if len(F) and (F.min() < 0 or F.max() >= len(V)):
            raise InputError(f"fusion: input {i} ({x.name!r}) has face indices out of range")
    for a in actions:
        if a.kind not in ("replace", "attach"):
            raise InputError(f"fusion: action kind {a.kind!r}, expected 'replace' or 'attach'")
        if not (0 <= a.a < len(inputs) and 0 <= a.b < len(inputs)) or a.a == a.b:
            raise InputError(f"fusion: action {a} must name two different inputs")


@dataclass(frozen=True)
class _Partition:
    """Which welded faces of each input the output keeps and which the junction replaces.

    Attributes
    ----------
    pres : list of Presence
        One per input.
    preserved : list of (m_i,) bool arrays
        Faces copied unchanged into the output.
    copied : list of (m_i,) bool arrays
        Junction faces copied as they are (both inputs of an action have them).
    kept : list of (m_i,) bool arrays
        ``preserved | copied``: both bound the junction (a copied face's vertices still get
        junction weights).
    junction : list of (m_i,) bool arrays
        Faces the junction surface replaces.
    h0 : float
        Coarsest voxel, ``voxel_factor`` times the smallest average edge length.
    diagonal : float
        Smallest input's bounding-box diagonal (0 without vertices).
    surfaces : list of (g_i, 3) int64 arrays
        Per input, its non-secondary welded faces prepared for signed distances
        (:func:`.fields.prepare_surface`): secondary components are kept whole or dropped, never
        blended, so they are in no field.
    """

    pres: list
    preserved: list
    copied: list
    kept: list
    junction: list
    h0: float
    diagonal: float
    surfaces: list


def _partition(inputs, actions, params) -> _Partition:
    """Presence of each input, then its preserved, copied and junction faces.

    Preserved faces that conflict with the other input (attach, burial), that leave the
    junction a thin wedge, that come too close to another seam, that form specks or pinch the
    seam join the junction; a preserved face two inputs share is kept from one of them; a
    junction cluster that two inputs share face for face is copied.
    """
    pres = [compute_presence(x.V, x.F, x.W, x.used, snap=params.snap, iterations=params.smooth_iterations,
                             alpha=params.smooth_alpha, preserve_threshold=params.preserve_threshold,
                             morphology_rounds=params.morphology_rounds,
                             secondary_variance=params.secondary_variance, replaced=x.replaced,
                             replaced_present=params.replaced_present) for x in inputs]
    edge_lengths = [average_edge_length(P.welded.V, P.welded.F) for P in pres]
    h0 = params.voxel_factor * min([e for e in edge_lengths if e > 0] or [1.0])
    diagonal = min([bounding_box_diagonal(P.welded.V) for P in pres if len(P.welded.V)] or [0.0])
    surfaces = [prepare_surface(P.welded.V, P.welded.F[~P.secondary]) for P in pres]
    preserved = attach_conflicts(pres, actions, h0 * params.attach_conflict_voxels / 2.0, surfaces)
    if params.min_seam_wedge > 0:
        preserved = [open_notches(P, preserved[i], min_wedge=params.min_seam_wedge) for i, P in enumerate(pres)]
    junction = [~preserved[i] & ~(P.absent & ~P.preserved) for i, P in enumerate(pres)]
    if len(pres) > 1 and any(j.any() for j in junction):
        # the finest voxel any junction will get bounds the room the cut needs between seams
        boxes0 = junction_clusters(pres, junction, params.margin_voxels * h0)
        h_est = min(cluster_grid(lo, hi, h0, params, diagonal).voxel for lo, hi in boxes0)
        preserved = separate_seams(pres, preserved, (2.0 * params.cut_voxels + 1.5) * h_est)
        preserved = drop_specks(pres, preserved, params.min_island_faces)
        preserved = unpinch_preserved(pres, preserved)
        if params.shell_clearance_voxels > 0:
            preserved = under_kept_shells(pres, preserved, junction)
        if params.min_seam_wedge > 0:
            preserved = [open_notches(P, preserved[i], min_wedge=params.min_seam_wedge) for i, P in enumerate(pres)]
        junction = [~preserved[i] & ~(P.absent & ~P.preserved) for i, P in enumerate(pres)]
    if len(pres) > 1:
        preserved = shared_preserved(pres, preserved, actions)
    copied = [np.zeros(len(P.welded.F), bool) for P in pres]
    if params.copy_coincident and len(pres) > 1:
        copied, dropped = coincident_faces(pres, preserved, junction, actions, params.margin_voxels * h0)
        junction = [junction[i] & ~copied[i] & ~dropped[i] for i in range(len(pres))]
    kept = [preserved[i] | copied[i] for i in range(len(pres))]
    return _Partition(pres=pres, preserved=preserved, copied=copied, kept=kept, junction=junction, h0=h0,
                      diagonal=diagonal, surfaces=surfaces)


def _seam_loops(part: _Partition):
    """Seam loops of every input (:func:`.seams.preserved_loops` on its kept faces, less the
    edges the other inputs' kept faces close) and the number of seam edges on open chains."""
    loops_all, open_chain_edges = [], 0
    kept = [(P.welded.V, P.welded.F[part.kept[i]]) for i, P in enumerate(part.pres)]
    for i, P in enumerate(part.pres):
        L, c = preserved_loops(P, part.kept[i], i, others=kept[:i] + kept[i + 1:])
        loops_all += L
        open_chain_edges += c
    return loops_all, open_chain_edges


def _seamless(part: _Partition, loops_all, open_chain_edges) -> bool:
    """Whether the inputs' kept faces close each other: no seam loop or chain left open (a
    symmetric character's limb replaced by its mirrored partner meets the body edge to edge),
    and every input with junction faces keeps some (a graft smaller than the voxel is all
    junction and has no seam either: it must not vanish). Then no junction is needed."""
    return (not loops_all and open_chain_edges == 0
            and all(np.any(k) for k, j in zip(part.kept, part.junction) if np.any(j)))


def _cluster_fields(grid, band, pres, surfaces, backend):
    """Signed distance and presence of each input near ``grid``, at its samples.

    Inputs with no surface within ``band`` of the grid get none. Inputs with the same geometry
    (a character composed with itself) share one distance computation.

    Returns
    -------
    dict
        Input -> ``(d, p)``, each ``(grid.size,)`` float.
    """
    fields = {}
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
    return fields


def _shells_near(grid, band, pres, shells):
    """Per input, its kept closed parts (:func:`kept_shells`) whose box meets ``grid`` grown by
    ``band``; empty arrays elsewhere."""
    out = []
    for i, P in enumerate(pres):
        Fs = shells[i]
        if len(Fs):
            X = P.welded.V[Fs].reshape(-1, 3)
            if np.any(X.min(axis=0) > grid.upper + band) or np.any(X.max(axis=0) < grid.origin - band):
                Fs = Fs[:0]
        out.append(Fs)
    return out


def _shell_clearance(grid, band, pres, shells, backend, clearance_voxels):
    """Lower bound of the blended field that keeps the junction out of the kept closed parts.

    ``clearance - d``, ``d`` the signed distance to the parts (negative inside), ``clearance``
    ``clearance_voxels`` voxels: positive (outside the junction's solid) inside a part
    and within the clearance around it, so that the isosurface of ``max(field, bound)`` goes
    around a part it would have passed through (the solid minus the part), and is unchanged
    farther away.

    Parameters
    ----------
    grid : Grid
    band : float
        Distances are exact within ``band`` of a part.
    pres : list of Presence
    shells : list of (s_i, 3) int arrays
        Per input, welded faces of its kept closed parts near ``grid`` (:func:`_shells_near`).
    backend : the field backend
    clearance_voxels : float

    Returns
    -------
    (grid.size,) float64 or None
        None when no part is near the grid.
    """
    out = None
    clearance = clearance_voxels * grid.voxel
    for i, P in enumerate(pres):
        Fs = shells[i]
        if not len(Fs):
            continue
        d, _ = backend.signed_distance(grid, P.welded.V, Fs, np.zeros((len(P.welded.V), 1)), band=band)
        bound = clearance - d
        out = bound if out is None else np.maximum(out, bound)
    return out


@dataclass(frozen=True)
class _ClusterResult:
    """One junction cluster's contribution to the output.

    Attributes
    ----------
    V : (k, 3) float64, F : (q, 3) int64
        Junction surface (empty after the face-selection fallback).
    info : dict
        The report's grid entry.
    selected : list of (m_i,) bool arrays or None
        Per input, faces kept by the face-selection fallback.
    field : (name, Grid, float32 array) or None
        The blended field, with ``FusionParams.keep_fields``.
    timings : dict
        Seconds: ``fields``, then those of :class:`.stitch.ClusterJunction`.
    input_fields : dict or None
        The inputs' fields at the cluster's samples (:func:`_cluster_fields`), kept only for a
        second pass around kept parts (:func:`_around_kept_parts`), which uses the same grid.
    """

    V: np.ndarray
    F: np.ndarray
    info: dict
    selected: list | None
    field: tuple | None
    timings: dict
    input_fields: dict | None = None


def _fuse_cluster(ci, lo, hi, part, surfaces, loops_all, backend, actions, params,
                  shells=None, input_fields=None, keep_input_fields=False, seamless=False) -> _ClusterResult | None:
    """Fields and junction surface of cluster ``ci`` (box ``lo``, ``hi``); with ``shells`` (per
    input, welded faces of its kept closed parts: :func:`kept_shells`), a junction that goes
    around those near the cluster (:func:`_shell_clearance`), None when none is near.
    ``input_fields``: the inputs' fields of this cluster from an earlier pass (computed when
    None); ``keep_input_fields``: return them with the result; ``seamless``: the inputs' kept
    faces close each other (:func:`_seamless`).

    Where the isosurface cannot close the junction (open sheets have no inside; loops left
    unmatched), the cluster's input faces are kept instead from the input most present on each
    (:func:`.seams.most_present_faces`); where the composition is ``seamless``, the junction is
    empty.
    """
    pres = part.pres
    grid = cluster_grid(lo, hi, part.h0, params, part.diagonal)
    band = params.band_voxels * grid.voxel
    near = None if shells is None else _shells_near(grid, band, pres, shells)
    if near is not None and not any(len(Fs) for Fs in near):
        return None
    t0 = time.perf_counter()
    fields = _cluster_fields(grid, band, pres, surfaces, backend) if input_fields is None else input_fields
    clearance = None
    if near is not None:
        clearance = _shell_clearance(grid, band, pres, near, backend, params.shell_clearance_voxels)
    t_fields = time.perf_counter() - t0
    lo_g, hi_g = grid.origin, grid.upper
    cl = [L for L in loops_all
          if np.all(L.positions.mean(axis=0) >= lo_g) and np.all(L.positions.mean(axis=0) <= hi_g)]
    edge = local_edge_length(pres, part.junction, grid)

    def junction(loops):
        return junction_for_cluster(grid, pres, surfaces, part.kept, loops, fields, actions, params, band, edge,
                                    junction_masks=part.junction, diagonal=part.diagonal, floor=clearance)

    cj = junction(cl)
    if cj.info["unmatched_preserved_loops"] > 0 and any(L.hole_edges for L in cl):
        # a seam closed along a hole that the isosurface does not meet: left open as a chain
        # (counted in open_seam_edges), rather than the whole cluster picked from the inputs
        alt = junction([L for L in cl if not L.hole_edges])
        if alt.info["unmatched_preserved_loops"] == 0:
            cj = alt
            cj.info["seams_left_open"] = sum(len(L.vertices) - L.hole_edges for L in cl if L.hole_edges)
    info = {**cj.info, "voxel_size": grid.voxel, "voxels": grid.size, "shape": list(grid.shape), "loops": len(cl)}
    if clearance is not None:
        info["shell_clearance"] = True
    JV, JF, selected = cj.V, cj.F, None
    if info["unmatched_preserved_loops"] > 0 or (len(JF) == 0 and not seamless):
        selected = most_present_faces(pres, part.junction, grid)
        info["fallback"] = "face-selection"
        JV, JF = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    kept_field = (f"junction_{ci}", grid, cj.field.astype(np.float32)) if params.keep_fields else None
    return _ClusterResult(V=JV, F=JF, info=info, selected=selected, field=kept_field,
                          timings={"fields": t_fields, **cj.timings},
                          input_fields=fields if keep_input_fields else None)


@dataclass(frozen=True)
class _InputPart:
    """The faces of one input copied into the output: preserved ones, then fallback-selected
    and copied ones.

    Attributes
    ----------
    vertices : (k,) int64
        Split vertices used, in source order; the output's vertices ``base .. base + k``.
    faces : (f,) int64
        Split faces, preserved first, then the others, each in source order.
    F : (f, 3) int64
        Those faces over the output's vertices.
    extra : (start, count)
        Output faces ``start .. start + count`` are fallback-selected or copied (junction faces).
    copied_faces : (c,) int64
        Output indices of the copied faces.
    junction_vertices : (k,) bool
        Vertices whose weights the weights stage computes: those of copied faces where no
        preserved (or fallback-selected) face of the input keeps the position.
    """

    vertices: np.ndarray
    faces: np.ndarray
    F: np.ndarray
    extra: tuple
    copied_faces: np.ndarray
    junction_vertices: np.ndarray


def _input_part(x, P, preserved, selected, copied, base, face_base) -> _InputPart:
    """The part of input ``x`` (presence ``P``) in the output, its first vertex at ``base`` and its
    first face at ``face_base``."""
    extra = (selected | copied) & ~preserved
    fidx = np.concatenate([np.flatnonzero(preserved), np.flatnonzero(extra)])
    start = face_base + int(np.count_nonzero(preserved))
    Fi = np.asarray(x.F, np.int64)[fidx]
    vidx = np.unique(Fi.ravel())
    # a copied face's vertices get junction weights, except where the input keeps the
    # position on a preserved (or fallback-selected) face: those keep the input's weights
    W_ = P.welded
    keeps = np.zeros(len(W_.V), bool)
    keeps[W_.F[preserved | (selected & ~copied)].ravel()] = True
    on_copied = np.zeros(len(x.V), bool)
    on_copied[np.asarray(x.F, np.int64)[copied].ravel()] = True
    remap = np.full(len(x.V), -1, np.int64)
    remap[vidx] = base + np.arange(len(vidx))
    return _InputPart(vertices=vidx, faces=fidx, F=remap[Fi], extra=(start, int(np.count_nonzero(extra))),
                      copied_faces=start + np.flatnonzero(copied[extra]),
                      junction_vertices=(on_copied & ~keeps[W_.index])[vidx])


def _junction_sources(inputs, pres, Q, n_generated, h0, with_colors):
    """Closest points on each input of the vertices whose weights the weights stage computes,
    and the presence-weighted colours of the generated junction vertices.

    Parameters
    ----------
    Q : (q, 3) float array
        Those vertices; the generated ones are the last ``n_generated``.
    h0 : float
        Coarsest voxel; ``1e-3 h0`` keeps the inverse-distance colour weights finite.
    with_colors : bool

    Returns
    -------
    sources : list of dict
        Per input, ``face``, ``bary``, ``distance`` and ``presence`` (see
        :attr:`FusedSurface.junction_sources`).
    colors : (n_generated, 4) float64 or None
        Linear RGBA; white where no input is present.
    """
    import igl

    nq, nJ = len(Q), n_generated
    sources = []
    wsum = np.zeros(nJ)
    csum = np.zeros((nJ, 4))
    gen = slice(nq - nJ, nq)
    for i, x in enumerate(inputs):
        if nq == 0:
            sources.append({"face": np.zeros(0, np.int64), "bary": np.zeros((0, 3)), "distance": np.zeros(0),
                            "presence": np.zeros(0)})
            continue
        Vx = np.asarray(x.V, np.float64)
        Fx = np.asarray(x.F, np.int64)
        d2, fid, C = igl.point_mesh_squared_distance(Q, Vx, Fx)
        T = Fx[fid]
        B = igl.barycentric_coordinates(C, Vx[T[:, 0]], Vx[T[:, 1]], Vx[T[:, 2]])
        B = np.clip(np.nan_to_num(B, nan=1 / 3), 0, 1)
        B /= np.maximum(B.sum(axis=1, keepdims=True), 1e-12)
        p = np.einsum("nk,nk->n", B, pres[i].p[T])
        sources.append({"face": fid, "bary": B, "distance": np.sqrt(d2), "presence": p})
        if with_colors and nJ:
            cx = np.asarray(x.colors, np.float64) if x.colors is not None else np.ones((len(Vx), 4))
            w = p[gen] / (np.sqrt(d2[gen]) + 1e-3 * h0)
            csum += w[:, None] * np.einsum("nk,nkc->nc", B[gen], cx[T[gen]])
            wsum += w
    colors = None
    if with_colors:
        colors = csum / np.maximum(wsum, 1e-12)[:, None]
        colors[wsum <= 0] = 1.0
    return sources, colors


def _output_parts(inputs, part: _Partition, selected) -> list:
    """Each input's faces in the output (:class:`_InputPart`), numbered one input after the other.

    ``selected``: per input, the ``(m_i,)`` bool faces kept by the face-selection fallback.
    """
    parts = []
    base = face_base = 0
    for i, x in enumerate(inputs):
        parts.append(_input_part(x, part.pres[i], part.preserved[i], selected[i], part.copied[i], base, face_base))
        base += len(parts[-1].vertices)
        face_base += len(parts[-1].faces)
    return parts


def _assemble(inputs, part: _Partition, selected, JV, JF, fields) -> FusedSurface:
    """The output surface, without its report: each input's parts (:func:`_output_parts`), then
    the junction surface ``JV`` (k, 3), ``JF`` (q, 3), with their attributes.

    ``selected``: per input, the ``(m_i,)`` bool faces kept by the face-selection fallback;
    ``fields``: the kept blended fields (:attr:`FusedSurface.fields`).
    """
    import igl

    pres, h0 = part.pres, part.h0
    has_uv = all(x.uvs is not None for x in inputs)
    has_n = all(x.normals is not None for x in inputs)
    has_c = any(x.colors is not None for x in inputs)
    parts = _output_parts(inputs, part, selected)
    Vs = [np.asarray(x.V, np.float64)[q.vertices] for x, q in zip(inputs, parts)] + [JV]
    base = sum(len(q.vertices) for q in parts)
    Fs_out = [q.F for q in parts] + [np.asarray(JF, np.int64).reshape(-1, 3) + base]
    n_pres_faces = sum(len(q.faces) for q in parts)
    jstart = base
    nJ = len(JV)
    V_out = np.concatenate(Vs)
    F_out = np.concatenate(Fs_out).astype(np.int64)
    n_generated_faces = len(F_out) - n_pres_faces
    junction_faces = np.zeros(len(F_out), bool)
    junction_faces[n_pres_faces:] = True
    for start, count in (q.extra for q in parts):
        junction_faces[start:start + count] = True
    copied_faces = np.zeros(len(F_out), bool)
    copied_faces[np.concatenate([q.copied_faces for q in parts]).astype(np.int64)] = True
    junction_vertices = np.concatenate([q.junction_vertices for q in parts] + [np.ones(nJ, bool)])

    # junction attributes: closest points on each input (for every vertex whose weights the
    # weights stage computes), presence-weighted colours (generated vertices: the last nJ rows)
    sources, jc = _junction_sources(inputs, pres, V_out[np.flatnonzero(junction_vertices)], nJ, h0, has_c)
    uvs = normals = colors = None
    if has_uv:
        uvs = np.concatenate([np.asarray(x.uvs, np.float64)[q.vertices] for x, q in zip(inputs, parts)]
                             + [np.zeros((nJ, 2))])
    if has_n:
        JVall, JFall = V_out[jstart:], F_out[n_pres_faces:] - jstart
        jn = igl.per_vertex_normals(JVall, JFall) if len(JFall) else np.zeros((nJ, 3))
        normals = np.concatenate([np.asarray(x.normals, np.float64)[q.vertices] for x, q in zip(inputs, parts)]
                                 + [np.nan_to_num(np.asarray(jn))])
    if has_c:
        colors = np.concatenate([np.asarray(x.colors, np.float64)[q.vertices] if x.colors is not None
                                 else np.ones((len(q.vertices), 4)) for x, q in zip(inputs, parts)] + [jc])
    mesh_of_vertex = [np.asarray(x.mesh_of_vertex)[q.vertices] if x.mesh_of_vertex is not None
                      else np.zeros(len(q.vertices), np.int64) for x, q in zip(inputs, parts)]
    return FusedSurface(
        V=V_out, F=F_out,
        origin_input=np.concatenate([np.full(len(q.vertices), i) for i, q in enumerate(parts)]
                                    + [np.full(nJ, -1)]).astype(np.int64),
        origin_vertex=np.concatenate([q.vertices for q in parts] + [np.full(nJ, -1)]).astype(np.int64),
        face_origin_input=np.concatenate([np.full(len(q.faces), i) for i, q in enumerate(parts)]
                                         + [np.full(n_generated_faces, -1)]).astype(np.int64),
        face_origin_face=np.concatenate([q.faces for q in parts] + [np.full(n_generated_faces, -1)]).astype(np.int64),
        junction_faces=junction_faces, preserved=tuple(part.preserved), presence=tuple(P.p for P in pres),
        mesh_of_vertex=np.concatenate(mesh_of_vertex + [np.full(nJ, -1)]).astype(np.int64),
        uvs=uvs, normals=normals, colors=colors, junction_sources=tuple(sources),
        fields=tuple(fields), junction_vertices=junction_vertices, copied_faces=copied_faces,
    )


def _fallbacks(clusters) -> int:
    """Clusters whose junction is input faces kept instead of a closed isosurface."""
    return sum(1 for c in clusters if c.info.get("fallback"))


def _made(repaired) -> int:
    """Crossing pairs left after the repair that no input had: not a kept face through its own
    input (:attr:`_Repaired.layered`)."""
    return repaired.left - repaired.layered


def _overused_edges(F) -> int:
    """Edges of the faces ``F`` (q, 3) shared by more than two of them."""
    _, counts = edge_counts(F)
    return int(np.count_nonzero(counts > 2))


def _repair_clusters(inputs, part: _Partition, clusters, params) -> _Repaired:
    """The clusters' junctions and fallback-selected faces as one surface, its crossing faces
    repaired (:func:`_repair_crossings`)."""
    selected = [np.zeros(len(P.welded.F), bool) for P in part.pres]
    for c in clusters:
        if c.selected is not None:
            selected = [s | c.selected[i] for i, s in enumerate(selected)]
    JV, JF = _junction_geometry(clusters)
    return _repair_crossings(inputs, part, selected, JV, JF, params)


def _around_kept_parts(inputs, part: _Partition, boxes, clusters, repaired: _Repaired, shells, surfaces,
                       loops_all, backend, actions, params, seamless=False):
    """The junction made again around the closed parts the inputs keep whole (:func:`kept_shells`),
    in the clusters near one whose junction has a crossing no input had, where it leaves fewer
    such crossing pairs than ``repaired``, no more clusters falling back to face selection, no
    more over-shared edges, and triangles as good (the 5th percentile of the junction's minimum
    angles at least the smaller of ``min_angle_p05`` and the first junction's).

    ``shells``: per input, :func:`kept_shells`; the clusters' ``input_fields`` are used again.

    Returns
    -------
    clusters : list of _ClusterResult
    repaired : _Repaired
        Those given where nothing is better.
    """
    if not any(len(Fs) for Fs in shells):
        return clusters, repaired
    offsets = np.cumsum([0] + [len(c.F) for c in clusters])
    crossing = [bool(repaired.made[a:b].any()) for a, b in zip(offsets[:-1], offsets[1:])]
    carved = [_fuse_cluster(ci, lo, hi, part, surfaces, loops_all, backend, actions, params, shells=shells,
                            input_fields=clusters[ci].input_fields, seamless=seamless) if crossing[ci] else None
              for ci, (lo, hi) in enumerate(boxes)]
    if all(c is None for c in carved):
        return clusters, repaired
    carved = [c if c is not None else o for c, o in zip(carved, clusters)]
    alt = _repair_clusters(inputs, part, carved, params)
    floor = min(params.min_angle_p05, _angle_p05(repaired.JV, repaired.JF))
    if (_made(alt) < _made(repaired) and _fallbacks(carved) <= _fallbacks(clusters)
            and _overused_edges(alt.JF) <= _overused_edges(repaired.JF) and _angle_p05(alt.JV, alt.JF) >= floor):
        return carved, alt
    return clusters, repaired


def _angle_p05(V, F) -> float:
    """5th percentile of the minimum angles of the triangles ``F`` over ``V`` (degrees; 90 for
    none)."""
    from .meshutil import triangle_min_angles

    return float(np.percentile(triangle_min_angles(V, F), 5)) if len(F) else 90.0


def _junction_geometry(clusters):
    """The clusters' junction surfaces as one: ``(JV (k, 3), JF (q, 3))``."""
    JV = np.concatenate([c.V for c in clusters]) if clusters else np.zeros((0, 3))
    offsets = np.cumsum([0] + [len(c.V) for c in clusters])
    JF = (np.concatenate([c.F + o for c, o in zip(clusters, offsets)]).astype(np.int64) if clusters
          else np.zeros((0, 3), np.int64))
    return JV, JF


@dataclass(frozen=True)
class _Repaired:
    """The fused surface after the repair of crossing faces (:func:`_repair_crossings`).

    Attributes
    ----------
    part : _Partition
        With the released kept faces no longer preserved nor copied.
    selected : list of (m_i,) bool arrays
        Fallback-selected faces, released ones excepted.
    JV : (k, 3) float64, JF : (q, 3) int64
        The junction surface, released faces included.
    found, left, layered, released : int
        Crossing pairs before and after, those left with overlapping input parts
        (:attr:`.crossings.CrossingRepair.layered`); kept faces that joined the junction.
    largest_move : float
        The farthest the repair moved a vertex (same units as the surface; 0 when none moved).
    made : (q0,) bool
        Over the clusters' junction faces before the repair (:func:`_junction_geometry`), those
        in a crossing left that no input had.
    """

    part: _Partition
    selected: list
    JV: np.ndarray
    JF: np.ndarray
    found: int
    left: int
    layered: int
    released: int
    made: np.ndarray
    largest_move: float = 0.0


def _crossing_own_input(part: _Partition, parts, faces):
    """``(k,) bool``: whether each kept output face of ``faces`` ``(k,)`` (numbered as
    :func:`_output_parts` numbers them) crosses a face of its own input (overlapping parts)."""
    from .meshutil import intersecting_face_pairs

    out = np.zeros(len(faces), bool)
    face_base = 0
    for i, q in enumerate(parts):
        mine = np.flatnonzero((faces >= face_base) & (faces < face_base + len(q.faces)))
        if len(mine):
            W_ = part.pres[i].welded
            src = q.faces[faces[mine] - face_base]
            out[mine] = np.isin(src, intersecting_face_pairs(W_.V, W_.F, src)[:, 0])
        face_base += len(q.faces)
    return out


def _inherited_crossings(surface, part: _Partition, pairs) -> int:
    """Of the crossing pairs ``pairs`` ``(p, 2)`` (faces of ``surface``, at least one a junction
    face), those the inputs already had.

    A pair is inherited when its face outside the junction is a kept input face that, in its own
    input, crosses a face the junction replaced: overlapping parts of a modular character (a head
    shell through the neck, a backpack through the back) pass through the junction that remeshed
    what they passed through. A face of a wholly kept piece that passes through its input's
    surface near the replaced one also is, where it lies against the replaced surface
    (:func:`.crossings.layer_faces`, within as far from it as the junction faces it crosses):
    the remeshed junction, which continues that surface, crosses the piece along about the same
    curve, at the piece's faces beside those that crossed. Pairs of two junction faces are never
    inherited.

    Parameters
    ----------
    surface : FusedSurface
        The assembled surface (``face_origin_input`` and ``face_origin_face`` number each input's
        welded faces).
    part : _Partition
        The partition the surface was assembled from (``kept`` after the crossing repair).
    """
    import igl

    from .crossings import layer_faces
    from .meshutil import intersecting_face_pairs

    junction = surface.junction_faces & ~surface.copied_faces
    pairs = pairs[~(junction[pairs[:, 0]] & junction[pairs[:, 1]])]  # two junction faces: never inherited
    outside = np.where(junction[pairs[:, 0]], pairs[:, 1], pairs[:, 0])
    inside = np.where(junction[pairs[:, 0]], pairs[:, 0], pairs[:, 1])
    inherited = np.zeros(len(surface.F), bool)
    for i, P in enumerate(part.pres):
        mine = surface.face_origin_input[outside] == i
        faces = np.unique(outside[mine])
        if not len(faces):
            continue
        src = surface.face_origin_face[faces]
        own = intersecting_face_pairs(P.welded.V, P.welded.F, src)
        first = np.isin(own[:, 0], src)
        me, other = np.where(first, own[:, 0], own[:, 1]), np.where(first, own[:, 1], own[:, 0])
        crossed_replaced = np.unique(me[~part.kept[i][other]])
        inherited[faces[np.isin(src, crossed_replaced)]] = True
        replaced = P.welded.F[~part.kept[i]]
        if len(replaced):
            corners = surface.V[surface.F[np.unique(inside[mine])]].reshape(-1, 3)
            d2, _, _ = igl.point_mesh_squared_distance(corners, P.welded.V, replaced)
            inherited[faces[layer_faces(P.welded.V, P.welded.F, part.kept[i], src,
                                        reach=float(np.sqrt(d2.max())))]] = True
    return int(inherited[outside].sum())


def _repair_crossings(inputs, part: _Partition, selected, JV, JF, params) -> _Repaired:
    """Junction faces that cross the surface, repaired (:func:`.crossings.repair_junction`):
    junction vertices move, and kept faces in the way may join the junction (their input faces
    stop being preserved, copied or selected). Nothing changes where nothing crosses."""
    from functools import partial

    from .crossings import repair_junction

    parts = _output_parts(inputs, part, selected)
    KV = np.concatenate([np.asarray(x.V, np.float64)[q.vertices] for x, q in zip(inputs, parts)])
    KF = np.concatenate([q.F for q in parts])
    counted = np.zeros(len(KF), bool)  # fallback-selected faces count as junction, copied ones do not
    for q in parts:
        start, count = q.extra
        counted[start:start + count] = True
        counted[q.copied_faces] = False
    rep = repair_junction(KV, KF, JV, JF, counted=counted, layered=partial(_crossing_own_input, part, parts),
                          rounds=params.crossing_rounds, min_angle=params.min_angle_p05)
    counts = {"found": rep.found, "left": rep.left, "layered": rep.layered, "released": int(rep.released.sum()),
              "made": rep.made, "largest_move": rep.largest_move}
    if not rep.released.any():
        return _Repaired(part=part, selected=selected, JV=rep.JV, JF=rep.JF, **counts)
    preserved = [p.copy() for p in part.preserved]
    copied = [c.copy() for c in part.copied]
    selected = [s_.copy() for s_ in selected]
    face_base = 0
    for i, q in enumerate(parts):
        gone = q.faces[rep.released[face_base:face_base + len(q.faces)]]
        preserved[i][gone] = copied[i][gone] = selected[i][gone] = False
        face_base += len(q.faces)
    kept = [preserved[i] | copied[i] for i in range(len(preserved))]
    return _Repaired(part=replace(part, preserved=preserved, copied=copied, kept=kept), selected=selected,
                     JV=rep.JV, JF=rep.JF, **counts)


def _surface_report(surface, part, inputs, infos, h0, backend_name, open_chain_edges):
    """The report's ``mesh`` (:func:`.report.mesh_report`, the junction counts and the inherited
    crossings, :func:`_inherited_crossings`) and ``fields`` (``infos``: the clusters' grid
    entries) parts."""
    from functools import partial

    mrep = mesh_report(surface.V, surface.F, surface.junction_faces & ~surface.copied_faces,
                       [(x.V, x.F) for x in inputs], inherited=partial(_inherited_crossings, surface, part))
    mrep["junction_faces"] = int(surface.junction_faces.sum())
    mrep["copied_faces"] = int(surface.copied_faces.sum())
    mrep["unmatched_loops"] = int(sum(inf["unmatched_preserved_loops"] for inf in infos))
    mrep["open_seam_edges"] = int(open_chain_edges) + sum(int(g.get("seams_left_open", 0)) for g in infos)
    fields = {
        "voxel_size": float(min([g["voxel_size"] for g in infos], default=h0)),
        "voxels": int(sum(g["voxels"] for g in infos)),
        "backend": backend_name,
        "grids": infos,
    }
    return mrep, fields


def fuse_surfaces(inputs: Sequence[FusionInput], actions: Sequence[FusionAction], *,
                  params: FusionParams = FusionParams(), step: Callable[[str], None] | None = None) -> FusedSurface:
    """Fuse the input surfaces into M_R = preserved parts + junction surface.

    Parameters
    ----------
    inputs : sequence of FusionInput
        Positioned rest-pose surfaces with their weights and kept joints.
    actions : sequence of FusionAction
        Which inputs meet and how (``replace``: presence-weighted blend of the signed distances;
        ``attach``: union). A junction no action covers (a removed subtree) is capped.
    params : FusionParams
    step : callable, optional
        ``step(name)`` as each sub-step starts (progress): ``"presence"``, ``"seams"``,
        ``"junction 1 of k"`` for each junction, ``"crossing repair"``, ``"around kept parts"``
        (when it runs), ``"assembly"``.

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
    t_all = time.perf_counter()
    inputs = list(inputs)
    actions = list(actions)
    _check_inputs(inputs, actions)
    check_coordinates({f"input {i} ({x.name!r})": x.V for i, x in enumerate(inputs)}, where="fusion",
                      fix="position the inputs within range (rigmix.operations)")
    step = step or (lambda name: None)
    t0 = time.perf_counter()
    step("presence")
    part = _partition(inputs, actions, params)
    timings = {"presence": time.perf_counter() - t0}

    t0 = time.perf_counter()
    step("seams")
    loops_all, open_chain_edges = _seam_loops(part)
    seamless = _seamless(part, loops_all, open_chain_edges)
    boxes = junction_clusters(part.pres, part.junction, params.margin_voxels * part.h0)
    backend = get_backend(params.backend)
    surfaces = part.surfaces
    timings["setup"] = time.perf_counter() - t0

    shells = None
    if params.shell_clearance_voxels > 0:
        shells = [kept_shells(P, part.kept[i]) for i, P in enumerate(part.pres)]
    second_pass = shells is not None and any(len(Fs) for Fs in shells)
    clusters = []
    for ci, (lo, hi) in enumerate(boxes):
        step(f"junction {ci + 1} of {len(boxes)}")
        clusters.append(_fuse_cluster(ci, lo, hi, part, surfaces, loops_all, backend, actions, params,
                                      keep_input_fields=second_pass, seamless=seamless))
    for c in clusters:
        for k, v in c.timings.items():
            timings[k] = timings.get(k, 0.0) + v
    t0 = time.perf_counter()
    step("crossing repair")
    repaired = _repair_clusters(inputs, part, clusters, params)
    timings["crossings"] = time.perf_counter() - t0
    if second_pass and _made(repaired) > 0:
        t0 = time.perf_counter()
        step("around kept parts")
        clusters, repaired = _around_kept_parts(inputs, part, boxes, clusters, repaired, shells, surfaces,
                                                loops_all, backend, actions, params, seamless)
        timings["shell_clearance"] = time.perf_counter() - t0
    clusters = [replace(c, input_fields=None) for c in clusters]  # free them before assembly
    for ci, c in enumerate(clusters):
        if c.info.get("fallback"):
            log.warning("fusion: junction %d could not be closed by the isosurface (%d loops left); "
                        "kept the most present input faces instead", ci, c.info["unmatched_preserved_loops"])
    t0 = time.perf_counter()
    step("assembly")
    surface = _assemble(inputs, repaired.part, repaired.selected, repaired.JV, repaired.JF,
                        [c.field for c in clusters if c.field is not None])
    timings["assembly"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    infos = [c.info for c in clusters]
    mrep, fields = _surface_report(surface, repaired.part, inputs, infos, part.h0, backend.name, open_chain_edges)
    mrep["junction_crossings_repaired"] = repaired.found - repaired.left
    mrep["junction_faces_released"] = repaired.released
    mrep["junction_crossings_layered"] = repaired.layered
    mrep["junction_repair_largest_move"] = repaired.largest_move
    timings["report"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    report = {"mesh": mrep, "fields": fields, "timings": {k: round(v, 4) for k, v in timings.items()}}
    return replace(surface, report=report)
