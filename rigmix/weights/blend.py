"""W_R: the skinning weights of a composed character (PIPELINE.md section 4).

:func:`blend_weights` is the weight stage of :func:`rigmix.pipeline.compose`:

1. retarget each input's weights through its bone map (:func:`.retarget.retarget_weights`: weights of
   input joints mapped to the same output joint are summed);
2. preserved vertices (copied from an input by the fusion) copy their retargeted row exactly;
3. junction vertices (made by the fusion) by one of three methods, all kept and compared by
   ``benchmarks/self_composition.py``:

``nearest``
    the paper's rule: the retargeted weights at the closest point of each input, interpolated
    by the blend factor (presence at that point, over distance).
``inpaint``
    the Robust Skin Weights Transfer anchor (Abdrashitov et al. 2023): a junction vertex is
    *matched* when its closest input point lies within ``match_distance`` x the bounding-box
    diagonal and the normals differ by at most ``match_angle`` degrees; matched vertices take
    the ``nearest`` weights, the others are inpainted (squared Laplacian, matched and
    preserved vertices fixed, smoothing) by :func:`rigmix.weights.fill_weights`, per connected
    component and never singular.
``dfd`` (default)
    the inputs' closest-point weights blended by *harmonic blend factors*
    (:func:`harmonic_blend_factors`: each junction vertex mixes the inputs by how close it is,
    along the surface, to each input's preserved part, so the transition spans the junction
    instead of jumping where the closest input changes, while each input's own weight profile,
    the artist's painting, is kept); matched as for ``inpaint`` but with a 90 degree normal
    tolerance (see ``match_angle``), and whatever the normals on an input's surface (within 0.5%
    of the diagonal, ``match_on_surface``); the rest (far or low-confidence vertices) filled by
    ``fill_weights(method="dfd")`` (prior borrowed from similar known parts, inpainting energy
    as regularizer) with *geodesic locality*: a joint keeps its weight on an unknown vertex
    only if the joint drives a known vertex (or, by the trusted mirror prior, a filled one)
    within a geodesic radius of it, so weights never leak to a look-alike part elsewhere (the
    other hand); a joint that deforms the inputs but no known vertex of the surface (its whole
    surface is filled: a head inside the junction band) keeps what the fill gives it.
    By default the mirror prior is trusted by the reflection distance alone. With
    ``feature_field=True`` (config ``[weights] feature_field = true``, CLI ``--feature-field``)
    the DFD feature field of the fused surface is distilled (:data:`FIELD_DISTILL`, a few
    seconds on two cores) and decides how far the mirror prior is trusted: a vertex borrows its
    mirror point's weights only where the two points look alike. It is off by default because
    it changes no measured figure (self-composition and band-fill benchmarks, the stretch ratio
    and roughness of every test config) for most of the composition's time.

Junction vertices whose mapping confidence (the confidence of the joints weighting their
closest input points) is below ``min_confidence`` are never matched: their weights are filled.
Every row of the result is non-negative, has at most ``max_influences`` non-zeros and sums to 1.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from dfd.mesh import smooth, vertex_normals, welded_graph

from ..errors import InputError, NumericalError
from ..fusion.inputs import check_dense_weights
from ..geometry import bounding_box_diagonal, weld
from ..sparse_weights import column_support, dense_rows, from_dense, positive_counts, row_blocks, row_sums, set_rows
from .fill import fill_weights
from .junction import continue_far_parts, harmonic_blend_factors, match_junction
from .mesh import sparsify
from .mirror import feature_field as distill_feature_field
from .params import WeightParams
from .retarget import blend_parts, closest_point_weights, retarget_inputs

__all__ = ["blend_weights", "SkinWeights", "WEIGHT_METHODS", "BLEND_FACTORS", "ON_SURFACE", "JUNCTION_SMOOTHING",
           "FIELD_DISTILL", "blend_factors", "junction_fill_options", "copy_preserved_rows", "JunctionBlend",
           "blend_junction", "match_junction_rows", "smooth_seam", "weights_report", "smooth_rows", "weld_consistent",
           "fill_junction", "sparsify_rows"]

log = logging.getLogger(__name__)

WEIGHT_METHODS = ("nearest", "inpaint", "dfd")
#: How the inputs' closest-point weights are blended at a junction vertex (``blend_weights``).
BLEND_FACTORS = ("paper", "harmonic")

#: Distance from an input, as a fraction of the bounding-box diagonal, within which a junction
#: vertex lies on the input's surface (the fusion's own fidelity target): ``dfd`` matches it
#: whatever the normals (``match_on_surface``), and the harmonic blend reads the input's weights
#: there as its own painting (:func:`continue_far_parts`).
ON_SURFACE = 0.005

#: Post-smoothing iterations of the ``dfd`` fill on a junction (``fill_weights``' ``iterations``:
#: the robust transfer paper's 10, on the rows no prior decides). A junction band is the fusion's
#: isosurface, meshed at the voxel size, and there the smoothing removes isolated wrong rows
#: (hidden self-compositions: mean junction weight error 0.198 with it, 0.203 without; mean
#: skinned error 2.51% and 2.78% of the diagonal; Knight shoulder 3.6% and 8.1%). On an artist's
#: coarser mesh it blurs the painting instead (band fill benchmark: 0.158 with it, 0.130
#: without), so ``fill_weights``' own default is 0.
JUNCTION_SMOOTHING = 10

#: Distillation settings of the feature field of ``dfd`` (:func:`dfd.distill.distill`): the
#: prototype's 24 views at 112 px instead of 224 (a quarter of the pixels) and 300 Adam steps of
#: 1024 pixels, the same ~7 passes over the covered pixels as the distiller's defaults (300 steps
#: of 4096 at 224 px). Measured on the Horse+Knight centaur's fused surface (19k welded vertices,
#: 2 CPU cores, busy machine): 4.5 to 7.6 s against 23 to 30 s with the distiller's defaults,
#: which would take the whole composition past the SkinMixer paper's 12 s average; with these
#: settings ``rigmix compose`` of the centaur takes 9.0 to 10.4 s (2.9 to 3.1 s without the
#: field). ``distill_options`` overrides them.
FIELD_DISTILL = {"n_views": 24, "resolution": 112, "steps": 300, "batch_size": 1024}


@dataclass(frozen=True)
class SkinWeights:
    """The weights of the fused surface.

    Attributes
    ----------
    W : (N, J_R) scipy.sparse.csr_matrix, float64
        Weights on the output joints, held per influence (canonical CSR, zeros not stored);
        rows non-negative, at most ``max_influences`` non-zeros, summing to 1.
    junction : (N,) bool
        Vertices whose weights were computed (``FusedSurface.junction_vertices``).
    matched : (N,) bool
        Junction vertices whose weights were transferred (known to the fill).
    method : str
    report : dict
        ``method``, ``blend`` (the blend factors), ``max_influences``, ``min_sum``, ``max_sum``, ``junction_vertices``,
        ``matched_vertices``, ``low_confidence_vertices``, ``seam_smoothed_vertices``,
        ``seam_welded_vertices`` (junction rows given their seam partner's weights,
        :func:`weld_consistent`), ``feature_field`` (dfd with a field asked for), ``feature_field_distilled`` (one was
        needed and distilled), ``feature_field_s`` (seconds).
    """

    W: np.ndarray
    junction: np.ndarray
    matched: np.ndarray
    method: str
    report: dict = field(default_factory=dict)


def weld_consistent(V, F, W, junction, max_influences=4):
    """Give every split copy of a position the same weights, so the seams cannot open under
    animation.

    A junction row at a position that a preserved row shares takes that row (the mean of the
    preserved rows there, which normally agree); junction rows sharing a position with no
    preserved row take their mean. Preserved rows never change.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    W : (n, J) float array or scipy.sparse matrix
        Rows summing to 1.
    junction : (n,) bool array
        Rows whose weights were computed (the others are copied from an input).
    max_influences : int

    Returns
    -------
    W : (n, J) float64 array, or a scipy.sparse.csr_matrix for a sparse ``W``
        (dense only over the rows that share a position with a junction row).
    changed : int
        Junction rows that changed.
    """
    W = sp.csr_matrix(W, dtype=np.float64) if sp.issparse(W) else np.asarray(W, np.float64).copy()
    junction = np.asarray(junction, bool)
    if not junction.any():
        return W, 0
    _, index, _ = weld(np.asarray(V, np.float64), np.asarray(F, np.int64).reshape(-1, 3))
    k = int(index.max()) + 1 if len(index) else 0
    fixed = ~junction
    n_fixed = np.bincount(index[fixed], minlength=k)
    n_junc = np.bincount(index[junction], minlength=k)
    rows = np.flatnonzero(junction & ((n_fixed[index] > 0) | (n_junc[index] > 1)))
    if not len(rows):
        return W, 0
    groups = np.unique(index[rows])
    pos = np.full(k, -1, np.int64)
    pos[groups] = np.arange(len(groups))
    src = np.flatnonzero(pos[index] >= 0)
    # rows that vote: the preserved ones where a group has any, else its junction rows
    vote = src[np.where(n_fixed[index[src]] > 0, fixed[src], junction[src])]
    S = np.zeros((len(groups), W.shape[1]))
    np.add.at(S, pos[index[vote]], dense_rows(W, vote))
    S /= np.bincount(pos[index[vote]], minlength=len(groups))[:, None]
    new = S[pos[index[rows]]]
    over = np.count_nonzero(new > 0, axis=1) > max_influences
    if over.any():
        new[over] = sparsify(new[over], max_influences)
    changed = np.abs(new - dense_rows(W, rows)).sum(axis=1) > 0
    if sp.issparse(W):
        W = set_rows(W, rows, new)
    else:
        W[rows] = new
    return W, int(changed.sum())


def smooth_rows(V, F, W, rows, *, iterations=10, alpha=0.5):
    """``w <- (1 - alpha) w + alpha mean(neighbours)`` on ``rows`` (others fixed), on the welded mesh.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    W : (n, J) float array
    rows : (n,) bool array
        Rows to smooth; split vertices of one position move together.
    iterations : int
    alpha : float
        Fraction of the way to the neighbours' mean per iteration (:func:`dfd.mesh.smooth`).

    Returns
    -------
    W : (n, J) float64
        Smoothed rows renormalized; other rows unchanged.
    """
    W = np.asarray(W, np.float64).copy()
    rows = np.asarray(rows, bool)
    if not rows.any() or iterations <= 0:
        return W
    Vw, index, G = welded_graph(V, F)
    k = len(Vw)
    Ww = np.zeros((k, W.shape[1]))
    cnt = np.bincount(index, minlength=k).astype(np.float64)
    np.add.at(Ww, index, W)
    Ww /= np.maximum(cnt, 1)[:, None]
    free = np.zeros(k, bool)
    free[index[rows]] = True
    Ww = smooth((G > 0).astype(np.float64), Ww, free, iterations=iterations, alpha=alpha)
    out = Ww[index[rows]]
    W[rows] = out / np.maximum(out.sum(axis=1, keepdims=True), 1e-12)
    return W


def blend_weights(surface, inputs, maps, num_output_joints, *, params: WeightParams | None = None,
                  skeleton=None, field=None, step=None):
    """W_R on the fused surface.

    The steps, each its own function: retarget every input's weights onto the output joints
    (:func:`retarget_inputs`); copy the preserved rows (:func:`copy_preserved_rows`); blend the
    inputs' closest-point weights on the junction (:func:`blend_junction`); match the junction
    vertices whose closest input point is trustworthy (:func:`match_junction_rows`); fill the
    others (:func:`rigmix.weights.fill_weights`, options from :func:`junction_fill_options`);
    smooth the seam where the inputs disagree (:func:`smooth_seam`); give split copies of one
    position the same weights (:func:`weld_consistent`); report (:func:`weights_report`).

    Parameters
    ----------
    surface : rigmix.fusion.FusedSurface
    inputs : sequence of rigmix.fusion.FusionInput
        The inputs given to the fusion, in the same order (their ``W`` on the input joints).
    maps : sequence of rigmix.mapping.BoneMap
        B_i per input, same order.
    num_output_joints : int
    params : WeightParams, optional
        The options (defaults: the project's ``dfd``); the Notes give the reasons for the defaults.
    skeleton : rigmix.character.Skeleton, optional
        The output skeleton, its rest pose in the surface's space. ``dfd`` takes its joints'
        names and rest positions for the joint mirror (instead of inferring it from the known
        weights) and its bones as a weak prior where a filled region has no mirror (a band
        across the symmetry plane: a tail's or a neck's root), and lets a reflection that lands
        away from the surface follow its bone onto the mirror bone (a rest pose that differs
        between the sides).
    field : optional
        A DFD feature field for the ``dfd`` fill (``fill_weights``' ``field``: an object with
        ``evaluate(points) -> (q, C)``, a callable, or ``False`` for none); overrides
        ``params.feature_field``.
    step : callable, optional
        ``step(name)`` as each sub-step starts (progress): ``"retarget"``, ``"junction blend"``,
        ``"junction fill"`` (when rows are filled), ``"seam smoothing"`` (when on), ``"weld"``.

    Returns
    -------
    SkinWeights

    Raises
    ------
    InputError
        Unknown method or blend, or inputs and maps that do not match the surface.
    NumericalError
        Non-finite weights (never expected; checked as the stage's contract).

    Notes
    -----
    The defaults of :class:`WeightParams`, and why (measured with the benchmarks named):

    ``match_angle``
        30 degrees for ``inpaint`` (the robust transfer paper), 90 for ``dfd``. The isosurface
        normals of a remeshed junction differ from the input's by more than 30 degrees on about
        one junction vertex in ten even where the surface is the input's own
        (self-compositions), and 30 degrees would hand correct closest-point weights to the
        fill. Self-composition benchmark: skinned error over 0.5% of the diagonal in 4 of 37
        cases at 60 degrees (up to 2.9%), none at 90; the cross-character stretch ratios barely
        depend on it (Horse+Knight centaur 1.21 at 60, 1.26 at 90; tail graft 1.04, 1.05).
    ``blend``
        ``"harmonic"`` for ``dfd`` (:func:`harmonic_blend_factors`), ``"paper"``
        (``presence / distance``, :func:`closest_point_weights`) for the others. Horse+Knight
        centaur / tail graft stretch ratio: paper 2.14 / 1.17, harmonic 1.18 / 0.99; on the
        mirrored self-compositions the harmonic factors keep the junction weight error low where
        the paper's factors jump (Velociraptor leg.L: 0.0002 harmonic, 0.034 paper; skinned
        0.02% and 2.3% of the diagonal). With ``"harmonic"``, an input's closest-point weights
        that jump from vertex to vertex far from it are continued from where they are its own
        (:func:`continue_far_parts`): beast_arms example, junction weight roughness max 0.17 with
        the continuation, 0.29 without (the inputs' own painting: 0.14); Horse+Knight centaur,
        roughness p99 0.34 with, 0.45 without.
    ``match_on_surface``
        0.005 (:data:`ON_SURFACE`) for ``dfd``, the fusion's own fidelity target: such a vertex
        is on the input's surface; 0 (off) for ``inpaint``. On the identity self-compositions
        it makes RiggedFigure arm.L's and the Fox head's junction weights exact; the centaur's
        stretch ratio is 1.19 with it (every vertex within the distance matched), 1.17 without.
    ``smoothing``
        0 for every method: smoothing the seam overwrites the artist's painting wherever the two
        inputs differ (mirrored self-compositions: mean junction weight error 0.51 on
        RiggedFigure's arm with 30 iterations, 0.07 without), and the harmonic blend factors
        already spread the transition over the junction.
    ``skeleton``
        Hidden protocol of the self-composition benchmark (every junction row filled), Fox mean
        junction weight error without / with it: tail 0.71 / 0.37, right leg 0.48 / 0.10;
        Velociraptor legs, whose rest pose steps forward with the left foot, 0.46 / 0.26 and
        0.58 / 0.25 with the bones followed.
    ``feature_field``
        ``dfd`` (default False): the field of the fused surface is distilled (settings
        :data:`FIELD_DISTILL`, or ``distill_options``; ``field_cache`` caches it) only when some
        junction vertex is filled and the surface has a mirror plane, and the mirror prior is
        trusted only where a vertex and its mirror point differ in features by no more than the
        known vertices differ from theirs (:func:`rigmix.weights.mirror.mirror_prior`). False:
        the prior is trusted by the reflection distance alone (no torch, no distillation).
    """
    params = WeightParams() if params is None else params
    blend = blend_factors(params)
    inputs, maps = list(inputs), list(maps)
    if len(inputs) != len(maps) or len(inputs) != len(surface.preserved):
        raise InputError(f"weights: {len(inputs)} inputs and {len(maps)} maps for a surface fused from "
                         f"{len(surface.preserved)} inputs")
    N, J = len(surface.V), int(num_output_joints)
    diag = bounding_box_diagonal(surface.V) if N else 1.0
    step = step or (lambda name: None)
    step("retarget")
    retargeted, confidence = retarget_inputs(inputs, maps, J, skeleton=skeleton, cut_reach=params.cut_joint_reach)
    options, lazy = junction_fill_options(params, surface, retargeted, diagonal=diag, skeleton=skeleton, field=field)
    junction = np.asarray(surface.junction_vertices, bool)
    jrows = np.flatnonzero(junction)
    W = copy_preserved_rows(surface, retargeted, J, max_influences=params.max_influences)
    matched = np.zeros(N, bool)
    low = np.zeros(N, bool)
    seam = np.zeros(N, bool)
    if len(jrows):
        step("junction blend")
        mix = blend_junction(surface, inputs, retargeted, confidence, blend=blend,
                             tolerance=params.match_distance * diag, diagonal=diag)
        low[jrows] = mix.confidence < params.min_confidence
        W = set_rows(W, jrows, sparsify(mix.W, params.max_influences))
        if params.method != "nearest":
            matched[jrows] = match_junction_rows(surface, inputs, params, diagonal=diag) & ~low[jrows]
            unknown = junction & ~matched
            if unknown.any() and (~unknown).any():
                step("junction fill")
                W = fill_junction(surface, W, unknown, params, options)
        if params.smoothing > 0:
            step("seam smoothing")
            W, seam = smooth_seam(surface, W, mix.spread, params)
    step("weld")
    W, welded_rows = weld_consistent(surface.V, surface.F, W, junction, params.max_influences)
    bad = ~np.isfinite(W.data)
    if bad.any():
        rows = np.unique(np.repeat(np.arange(N), np.diff(W.indptr))[bad])
        raise NumericalError(f"weights: method {params.method!r} produced non-finite weights on "
                             f"{len(rows)} vertices")
    report = weights_report(W, params.method, blend, junction=junction, matched=matched, low_confidence=low,
                            seam=seam, welded_rows=welded_rows, feature_field=options.get("field") is not False,
                            lazy=lazy)
    log.debug("weights: %s", report)
    return SkinWeights(W=W, junction=junction, matched=matched, method=params.method, report=report)


def fill_junction(surface, W, unknown, params: WeightParams, options):
    """The unknown junction rows of ``W`` filled (:func:`rigmix.weights.fill_weights`).

    The fill solves on the whole welded surface over every output joint, so it takes the
    weights as a dense ``(N, J_R)`` matrix: that one is held to
    :data:`rigmix.fusion.inputs.MAX_DENSE_WEIGHT_ENTRIES` (an :class:`InputError` naming the
    counts past it).

    Parameters
    ----------
    surface : rigmix.fusion.FusedSurface
    W : (N, J_R) scipy.sparse.csr_matrix
    unknown : (N,) bool array
        Rows to fill (some, not all).
    params : WeightParams
    options : dict
        :func:`junction_fill_options`.

    Returns
    -------
    (N, J_R) scipy.sparse.csr_matrix
        ``W`` with the unknown rows filled, the others unchanged.
    """
    check_dense_weights(W.shape[0], W.shape[1], "weights: the junction fill (dense over the fused surface)")
    rows = np.flatnonzero(unknown)
    filled = fill_weights(surface.V, surface.F, W.toarray(), unknown, method=params.method,
                          max_influences=params.max_influences, **options)
    return set_rows(W, rows, filled[rows])


def blend_factors(params: WeightParams) -> str:
    """The blend factors ``params`` asks for (``params.blend``, or the method's default).

    Raises
    ------
    InputError
        Unknown method or blend.
    """
    if params.method not in WEIGHT_METHODS:
        raise InputError(f"weights: unknown method {params.method!r}; use one of {', '.join(WEIGHT_METHODS)}")
    blend = params.blend
    if blend is None:
        blend = "harmonic" if params.method == "dfd" else "paper"
    if blend not in BLEND_FACTORS:
        raise InputError(f"weights: unknown blend {blend!r}; use one of {', '.join(BLEND_FACTORS)}")
    return blend


def junction_fill_options(params: WeightParams, surface, retargeted, *, diagonal, skeleton=None, field=None):
    """The options of the junction's fill (:func:`rigmix.weights.fill_weights`), as a new dict.

    The fill options ``params`` sets (:meth:`WeightParams.fill_options`); for ``dfd``, the
    feature field (``field``, else a :class:`_LazyField` of the surface with ``params``'
    ``field_cache`` and ``distill_options`` over :data:`FIELD_DISTILL`, else ``False`` without
    ``params.feature_field``), the skeleton's joint names, rest positions and parents, the
    joints that deform the inputs (``deforming_joints``), ``iterations`` (default
    :data:`JUNCTION_SMOOTHING`), the geodesic locality (``params.locality`` x ``diagonal``) and
    ``ambient_borrow``.

    Parameters
    ----------
    params : WeightParams
    surface : rigmix.fusion.FusedSurface
    retargeted : sequence of (n_i, J_R) scipy.sparse matrices
        Each input's retargeted weights (:func:`retarget_inputs`).
    diagonal : float
        Bounding-box diagonal of the surface.
    skeleton : rigmix.character.Skeleton, optional
    field : optional
        A feature field given by the caller.

    Returns
    -------
    options : dict
    lazy : _LazyField or None
        The field to distill on first use, when one was set up (the report reads it).
    """
    options = params.fill_options()
    lazy = None
    if field is not None:
        options = {**options, "field": field}
    elif params.method == "dfd" and params.feature_field:
        lazy = _LazyField(surface.V, surface.F, cache=params.field_cache,
                          options={**FIELD_DISTILL, **(params.distill_options or {})})
        options = {k: v for k, v in options.items() if k not in ("field_cache", "distill_options")}
        options = {**options, "field": lazy}
    elif params.method == "dfd":
        options = {**options, "field": False}
    if params.method != "dfd":
        return options, lazy
    skeleton_options = {} if skeleton is None else {
        "joint_names": list(skeleton.names),
        "joint_positions": skeleton.rest_worlds()[:, :3, 3],
        "joint_parents": np.asarray(skeleton.parents),
    }
    # what the locality may keep where no known vertex witnesses it
    deforming = np.any([column_support(Wr) for Wr in retargeted], axis=0)
    locality_options = {} if params.locality <= 0 else {
        "locality": params.locality * diagonal, "locality_power": params.locality_power}
    # the field's one measured gain: borrowing next to joints nowhere known (ambient_borrow_prior)
    ambient_options = {"ambient_borrow": params.ambient_borrow} if params.ambient_borrow > 0 else {}
    return {"iterations": JUNCTION_SMOOTHING, **options, **skeleton_options, "deforming_joints": deforming,
            **locality_options, **ambient_options}, lazy


def copy_preserved_rows(surface, retargeted, num_output_joints, *, max_influences):
    """The weights of the preserved vertices, copied from their input's retargeted rows.

    Parameters
    ----------
    surface : rigmix.fusion.FusedSurface
        ``origin_input`` and ``origin_vertex`` say where each preserved vertex comes from.
    retargeted : sequence of (n_i, J_R) scipy.sparse matrices (or float arrays)
    num_output_joints : int
    max_influences : int

    Returns
    -------
    W : (N, J_R) scipy.sparse.csr_matrix, float64
        Preserved rows exactly as retargeted, except those with more than ``max_influences``
        non-zeros or none (sparsified); junction rows empty. Held per influence.
    """
    N = len(surface.V)
    junction = np.asarray(surface.junction_vertices, bool)
    pres = np.flatnonzero(~junction)
    blocks, pick, base = [], np.zeros(N, np.int64), 0
    for i in range(len(retargeted)):
        rows = pres[surface.origin_input[pres] == i]
        blocks.append(sp.csr_matrix(retargeted[i])[surface.origin_vertex[rows]])
        pick[rows] = base + np.arange(len(rows))
        base += len(rows)
    blocks.append(sp.csr_matrix((1, num_output_joints)))  # the junction rows' empty row
    pick[junction] = base
    W = sp.vstack(blocks, format="csr")[pick]
    W.sort_indices()
    # rows copied from an input are exact; only rows with more influences than allowed change
    bad = np.flatnonzero(~junction & ((positive_counts(W) > max_influences) | (row_sums(W) <= 0)))
    return sparsify_rows(W, bad, max_influences) if len(bad) else W


def sparsify_rows(W, rows, max_influences):
    """``W`` (``(N, J)`` CSR) with ``rows`` (``(q,)`` int) sparsified (:func:`sparsify`), a dense
    block of rows at a time; a new CSR matrix."""
    rows = np.asarray(rows, np.int64)
    parts = [from_dense(sparsify(dense_rows(W, rows[b]), max_influences)) for b in row_blocks(len(rows), W.shape[1])]
    return set_rows(W, rows, sp.vstack(parts, format="csr") if parts else sp.csr_matrix((0, W.shape[1])))


class JunctionBlend(NamedTuple):
    """The inputs' closest-point weights blended on the junction (:func:`blend_junction`).

    Attributes
    ----------
    W : (q, J_R) float64
        Blended weights of the ``q`` junction vertices (``np.flatnonzero(junction)`` order),
        not sparsified.
    spread : (q,) float64
        How much the blended inputs disagree (:func:`blend_parts`).
    confidence : (q,) float64
        Mapping confidence of the joints weighting the closest input points, blended alike.
    """

    W: np.ndarray
    spread: np.ndarray
    confidence: np.ndarray


def blend_junction(surface, inputs, retargeted, confidence, *, blend, tolerance, diagonal) -> JunctionBlend:
    """The inputs' closest-point weights at the junction vertices, blended.

    Parameters
    ----------
    surface : rigmix.fusion.FusedSurface
        With ``junction_sources`` (closest point of each input per junction vertex).
    inputs : sequence of rigmix.fusion.FusionInput
        Their faces ``F``.
    retargeted : sequence of (n_i, J_R) float arrays
    confidence : sequence of (n_i,) float arrays
        Mapping confidence per input row (:func:`retarget_inputs`).
    blend : {"paper", "harmonic"}
        ``"paper"``: ``presence / distance`` (:func:`closest_point_weights`); ``"harmonic"``:
        :func:`harmonic_blend_factors`, with each input's far, jumping weights continued
        (:func:`continue_far_parts`).
    tolerance : float
        Inputs farther than the closest one by more than this do not contribute (units of ``V``).
    diagonal : float
        Bounding-box diagonal of the surface.

    Returns
    -------
    JunctionBlend
    """
    srcs = surface.junction_sources
    junction = np.asarray(surface.junction_vertices, bool)
    _, t, parts = closest_point_weights(srcs, retargeted, [x.F for x in inputs], tolerance=tolerance,
                                        return_parts=True)
    if blend == "harmonic":
        t, parts = _harmonic_blend(surface, retargeted, t, parts, diagonal=diagonal)
    Wn, spread = blend_parts(t, parts)
    cj = np.zeros(int(junction.sum()))
    for i, s in enumerate(srcs):
        T = np.asarray(inputs[i].F, np.int64)[np.asarray(s["face"], np.int64)]
        cj += t[:, i] * np.einsum("qk,qk->q", np.asarray(s["bary"]), confidence[i][T])
    return JunctionBlend(Wn, spread, cj)


def _harmonic_blend(surface, retargeted, t, parts, *, diagonal):
    """The harmonic blend factors ``(q, I)`` of the junction vertices, and the inputs' parts with
    their far, jumping rows continued (:func:`continue_far_parts`)."""
    N, n_inputs = len(surface.V), len(retargeted)
    junction = np.asarray(surface.junction_vertices, bool)
    jrows, pres = np.flatnonzero(junction), np.flatnonzero(~junction)
    T = np.zeros((N, n_inputs))
    T[pres, surface.origin_input[pres]] = 1.0
    T[jrows] = t
    graph = welded_graph(surface.V, surface.F)  # built once: at a million faces it is the cost
    t = harmonic_blend_factors(surface.V, surface.F, T, junction, graph=graph)[jrows]
    owned = [pres[surface.origin_input[pres] == i] for i in range(n_inputs)]
    known = [(r, sp.csr_matrix(retargeted[i])[surface.origin_vertex[r]]) for i, r in enumerate(owned)]
    parts = continue_far_parts(surface.V, surface.F, parts, [s["distance"] for s in surface.junction_sources],
                               junction, known, near=ON_SURFACE * diagonal, graph=graph)
    return t, parts


def match_junction_rows(surface, inputs, params: WeightParams, *, diagonal):
    """:func:`match_junction` on the junction vertices of ``surface``, with ``params``' tolerances.

    ``match_angle`` defaults to 30 degrees for ``inpaint`` and 90 for ``dfd``, ``match_on_surface``
    to :data:`ON_SURFACE` for ``dfd`` and 0 for ``inpaint``. A junction vertex copied from an input
    (a junction both inputs share) is matched whatever its normal says: box corners differ from
    every face normal by 45 degrees.

    Returns
    -------
    matched : (q,) bool
        In ``np.flatnonzero(surface.junction_vertices)`` order.
    """
    jrows = np.flatnonzero(np.asarray(surface.junction_vertices, bool))
    match_angle = params.match_angle
    if match_angle is None:
        match_angle = 30.0 if params.method == "inpaint" else 90.0
    on_surface = params.match_on_surface
    if on_surface is None:
        on_surface = ON_SURFACE if params.method == "dfd" else 0.0
    JN = vertex_normals(surface.V, surface.F)[jrows]
    m = match_junction(surface.V[jrows], JN, surface.junction_sources, [x.V for x in inputs], [x.F for x in inputs],
                       diagonal=diagonal, match_distance=params.match_distance, match_angle=match_angle,
                       on_surface=on_surface)
    return m | (np.asarray(surface.origin_input)[jrows] >= 0)


def smooth_seam(surface, W, spread, params: WeightParams):
    """Smooth the junction vertices where the blended inputs disagree.

    ``params.smoothing`` iterations of :func:`smooth_rows` on the junction vertices whose
    ``spread`` exceeds ``params.seam_spread``, grown by ``params.seam_rings`` rings within the
    junction (the other vertices fixed); the smoothed rows are sparsified.

    Parameters
    ----------
    surface : rigmix.fusion.FusedSurface
    W : (N, J_R) scipy.sparse.csr_matrix
    spread : (q,) float array
        Of the junction vertices (:class:`JunctionBlend`).
    params : WeightParams

    Returns
    -------
    W : (N, J_R) scipy.sparse.csr_matrix
    seam : (N,) bool
        The smoothed vertices.

    Raises
    ------
    InputError
        The smoothing averages over the whole welded surface, densely: past
        :data:`rigmix.fusion.inputs.MAX_DENSE_WEIGHT_ENTRIES` entries.
    """
    junction = np.asarray(surface.junction_vertices, bool)
    seam = np.zeros(len(surface.V), bool)
    seam[np.flatnonzero(junction)] = spread > params.seam_spread
    seam = _grow(surface.V, surface.F, seam, params.seam_rings) & junction
    if seam.any():
        check_dense_weights(W.shape[0], W.shape[1], "weights: the seam smoothing (dense over the fused surface)")
        rows = np.flatnonzero(seam)
        smoothed = smooth_rows(surface.V, surface.F, W.toarray(), seam, iterations=params.smoothing)
        W = set_rows(W, rows, sparsify(smoothed[rows], params.max_influences))
    return W, seam


def weights_report(W, method, blend, *, junction, matched, low_confidence, seam, welded_rows, feature_field, lazy):
    """The weights stage's report (:attr:`SkinWeights.report`).

    Parameters
    ----------
    W : (N, J_R) float array or scipy.sparse matrix
        The final weights.
    method, blend : str
    junction, matched, low_confidence, seam : (N,) bool arrays
    welded_rows : int
        Junction rows :func:`weld_consistent` changed.
    feature_field : bool
        The fill was given a feature field (or asked to distill one).
    lazy : _LazyField or None

    Returns
    -------
    dict
    """
    N = W.shape[0]
    s = row_sums(W)
    return {
        "method": method,
        "blend": blend,
        "max_influences": int(positive_counts(W).max()) if N else 0,
        "min_sum": float(s.min()) if N else 1.0,
        "max_sum": float(s.max()) if N else 1.0,
        "junction_vertices": int(junction.sum()),
        "matched_vertices": int(matched.sum()),
        "low_confidence_vertices": int(low_confidence.sum()),
        "seam_smoothed_vertices": int(seam.sum()),
        "seam_welded_vertices": int(welded_rows),
        "feature_field": bool(method == "dfd" and feature_field),
        "feature_field_distilled": bool(lazy is not None and lazy.field is not None),
        "feature_field_s": round(lazy.seconds, 3) if lazy is not None else 0.0,
    }


class _LazyField:
    """The DFD feature field of the fused surface, distilled on its first evaluation.

    The ``dfd`` fill evaluates it only when some junction vertex is filled and the surface has a
    mirror plane (the field judges the mirror prior); otherwise nothing is distilled. ``field``
    and ``seconds`` tell the report whether it was and what it cost.
    """

    def __init__(self, V, F, *, cache, options):
        self.V, self.F, self.cache, self.options = V, F, cache, options
        self.field = None
        self.seconds = 0.0

    def evaluate(self, X):
        """Unit features ``(q, C)`` at points ``(q, 3)`` of the fused surface's space."""
        if self.field is None:
            t0 = time.perf_counter()
            self.field = distill_feature_field(self.V, self.F, cache=self.cache, **self.options)
            self.seconds = time.perf_counter() - t0
            log.debug("weights: feature field distilled in %.2f s", self.seconds)
        return self.field.evaluate(X)


def _grow(V, F, mask, rings):
    """``mask`` grown by ``rings`` rings of the welded mesh."""
    if rings <= 0 or not mask.any():
        return mask
    Vw, index, G = welded_graph(V, F)
    m = np.zeros(len(Vw), bool)
    m[index[mask]] = True
    A = G > 0
    for _ in range(rings):
        m = m | (A @ m.astype(np.float64) > 0)
    return m[index]
