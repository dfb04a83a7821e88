"""W_R (issue 6): retargeting, junction methods, invariants, self-composition, stretch ratio."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp
from conftest import IN_COMPOSED_GROUP, ROOT, asset

from rigmix.errors import InputError
from rigmix.fusion import FusedSurface, FusionInput
from rigmix.fusion.inputs import MAX_DENSE_WEIGHT_ENTRIES
from rigmix.geometry import weld
from rigmix.mapping import BoneMap
from rigmix.sparse_weights import dense_rows
from rigmix.weights import WeightParams, symmetry_plane
from rigmix.weights.blend import WEIGHT_METHODS, blend_weights
from rigmix.weights.junction import continue_far_parts, harmonic_blend_factors, match_junction
from rigmix.weights.retarget import closest_point_weights, retarget_inputs, retarget_weights, to_influences

EXAMPLES = sorted((ROOT / "examples").glob("*.toml"))


def _sphere(n=12, m=16, r=1.0, c=(0.0, 0.0, 0.0)):
    """A closed UV sphere ``(V, F)`` with consistent outward orientation."""
    th = np.linspace(0, np.pi, n + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, m, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    V = np.c_[np.sin(T).ravel() * np.cos(P).ravel(), np.cos(T).ravel(), np.sin(T).ravel() * np.sin(P).ravel()]
    V = np.r_[[[0, 1, 0]], V, [[0, -1, 0]]] * r + np.asarray(c)
    F = []
    idx = lambda i, j: 1 + i * m + (j % m)  # noqa: E731
    for j in range(m):
        F.append([0, idx(0, j + 1), idx(0, j)])
        F.append([len(V) - 1, idx(n - 2, j), idx(n - 2, j + 1)])
    for i in range(n - 2):
        for j in range(m):
            F.append([idx(i, j), idx(i, j + 1), idx(i + 1, j)])
            F.append([idx(i, j + 1), idx(i + 1, j + 1), idx(i + 1, j)])
    return V, np.array(F, np.int64)


# ------------------------------------------------------------------------------------------
# Small cases with a known answer
# ------------------------------------------------------------------------------------------


def test_retarget_sums_the_weights_of_joints_mapped_to_one_output_joint():
    W = np.array([[0.5, 0.3, 0.2, 0.0], [0.0, 0.0, 0.4, 0.6], [1.0, 0.0, 0.0, 0.0]])
    target = np.array([1, 1, 0, -1])  # joints 0 and 1 -> output 1; joint 3 unmapped
    Wr, c = retarget_weights(W, target, 3, confidence=np.array([1.0, 0.5, 1.0, 0.0]))
    assert sp.issparse(Wr)  # per influence
    Wr = Wr.toarray()
    assert np.allclose(Wr, [[0.2, 0.8, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert np.allclose(c, [0.5 + 0.15 + 0.2, 0.4, 1.0])
    # a row that already sums to 1 is copied bit-identically
    assert Wr[2].tobytes() == np.array([0.0, 1.0, 0.0]).tobytes()


def test_closest_point_weights_follow_the_present_input():
    W0 = np.array([[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]])
    W1 = np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]])
    F = np.array([[0, 1, 2]])
    s0 = {"face": np.array([0, 0]), "bary": np.full((2, 3), 1 / 3), "distance": np.array([0.1, 0.1]),
          "presence": np.array([1.0, 0.5])}
    s1 = {"face": np.array([0, 0]), "bary": np.full((2, 3), 1 / 3), "distance": np.array([0.1, 0.1]),
          "presence": np.array([0.0, 0.5])}
    W, t = closest_point_weights([s0, s1], [W0, W1], [F, F], tolerance=1.0)
    assert np.allclose(W, [[1.0, 0.0], [0.5, 0.5]])
    assert np.allclose(t.sum(axis=1), 1)
    # a far input does not contribute even with presence 1
    s1far = {**s1, "distance": np.array([5.0, 5.0]), "presence": np.array([1.0, 1.0])}
    W, _ = closest_point_weights([s0, s1far], [W0, W1], [F, F], tolerance=1.0)
    assert np.allclose(W, [[1.0, 0.0], [1.0, 0.0]])


def _isolated_junction_case():
    """Input 0: a sphere weighted on 3 joints; the fused surface adds a far, separate sphere
    made only of junction vertices (no vertex of it can be matched)."""
    import igl

    V0, F0 = _sphere()
    rng = np.random.default_rng(0)
    W0 = np.zeros((len(V0), 3))
    W0[:, 0] = np.clip(V0[:, 1], 0, None)
    W0[:, 1] = np.clip(-V0[:, 1], 0, None)
    W0[:, 2] = 0.2 + 0.1 * rng.random(len(V0))
    W0 /= W0.sum(axis=1, keepdims=True)
    V1, F1 = _sphere(6, 8, r=0.3, c=(4.0, 0.0, 0.0))
    x = FusionInput(V=V0, F=F0, W=W0, used=np.ones(3, bool))
    n0, n1 = len(V0), len(V1)
    d2, fid, C = igl.point_mesh_squared_distance(V1, V0, F0)
    T = F0[fid]
    B = igl.barycentric_coordinates(C, V0[T[:, 0]], V0[T[:, 1]], V0[T[:, 2]])
    src = {"face": fid, "bary": B, "distance": np.sqrt(d2), "presence": np.ones(n1)}
    surf = FusedSurface(
        V=np.r_[V0, V1], F=np.r_[F0, F1 + n0], origin_input=np.r_[np.zeros(n0, int), -np.ones(n1, int)],
        origin_vertex=np.r_[np.arange(n0), -np.ones(n1, int)],
        face_origin_input=np.r_[np.zeros(len(F0), int), -np.ones(len(F1), int)],
        face_origin_face=np.r_[np.arange(len(F0)), -np.ones(len(F1), int)],
        junction_faces=np.r_[np.zeros(len(F0), bool), np.ones(len(F1), bool)], preserved=(np.ones(len(F0), bool),),
        presence=(np.ones(n0),), mesh_of_vertex=np.r_[np.zeros(n0, int), -np.ones(n1, int)], uvs=None,
        normals=None, colors=None, junction_sources=(src,))
    return surf, x, BoneMap("a", np.arange(3), np.ones(3))


def test_match_on_surface_ignores_normals_only_when_asked():
    # one input triangle in z = 0 (normal +z); junction vertices on it (distance 0) and 0.04 above,
    # all with normal -z (a flipped, remeshed crease): the normal test rejects all of them
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    F = np.array([[0, 1, 2]])
    JV = np.array([[0.2, 0.2, 0.0], [0.2, 0.2, 0.04]])
    JN = np.array([[0, 0, -1.0], [0, 0, -1.0]])
    src = [{"distance": np.array([0.0, 0.04]), "presence": np.ones(2), "face": np.zeros(2, int)}]
    args = (JV, JN, src, [V], [F])
    assert not match_junction(*args, diagonal=1.0, match_angle=90.0).any()  # the anchor, on_surface 0
    assert match_junction(*args, diagonal=1.0, match_angle=90.0, on_surface=0.02).tolist() == [True, False]
    JN[:] = [0, 0, 1.0]
    assert match_junction(*args, diagonal=1.0, match_angle=30.0).all()


def _tube(rings=7, m=8):
    """An open tube along y: ``rings`` rings of ``m`` vertices, ring ``i`` at height ``i``."""
    a = np.linspace(0, 2 * np.pi, m, endpoint=False)
    V = np.array([[np.cos(t), i, np.sin(t)] for i in range(rings) for t in a])
    F = []
    for i in range(rings - 1):
        for j in range(m):
            p, q = i * m + j, i * m + (j + 1) % m
            F += [[p, q, p + m], [q, q + m, p + m]]
    return V, np.array(F, np.int64)


def test_harmonic_blend_factors_ramp_across_the_junction():
    # ends fixed to input 0 (bottom ring) and input 1 (top ring); the junction's own factors
    # jump from one input to the other half-way: the harmonic factors ramp linearly instead
    V, F = _tube(rings=7, m=8)
    ring = np.repeat(np.arange(7), 8)
    # split copies of ring 3 (a UV seam): same positions, their own faces
    dup = np.flatnonzero(ring == 3)
    V2 = np.r_[V, V[dup]]
    F2 = F.copy()
    upper = np.isin(F2, dup) & (ring[F2].max(axis=1, keepdims=True) == 4)
    F2[upper] = len(V) + np.searchsorted(dup, F2[upper])
    ring2 = np.r_[ring, ring[dup]]
    free = (ring2 > 0) & (ring2 < 6)
    T = np.zeros((len(V2), 2))
    T[ring2 == 0, 0] = 1.0
    T[ring2 == 6, 1] = 1.0
    T[free, 0] = ring2[free] < 3
    T[free, 1] = 1.0 - T[free, 0]
    # a free triangle touching no fixed vertex keeps its factors
    V3 = np.r_[V2, [[5, 0, 0], [6, 0, 0], [5, 1, 0]]]
    F3 = np.r_[F2, [[len(V2), len(V2) + 1, len(V2) + 2]]]
    T3 = np.r_[T, [[0.3, 0.7]] * 3]
    free3 = np.r_[free, [True] * 3]
    out = harmonic_blend_factors(V3, F3, T3, free3)
    assert np.allclose(out[:len(V2), 1], ring2 / 6.0, atol=1e-9)  # linear in height, split copies equal
    assert np.allclose(out.sum(axis=1), 1.0) and np.all(out >= 0)
    assert np.array_equal(out[~free3], T3[~free3]) and np.array_equal(out[-3:], T3[-3:])


def test_continue_far_parts_replaces_jumping_far_rows_only():
    # tube rings 0 (preserved by the input, joint 0) .. 6; junction rings 1-5. The input's
    # closest point jumps around rings 3-5 (alternating joints 1 and 2 around the ring: a far
    # input's closest point flipping across its medial axis); rings 1-2 are near, their part
    # its own painting (joint 0 fading into joint 1)
    V, F = _tube(rings=7, m=8)
    ring = np.repeat(np.arange(7), 8)
    junction = ring > 0
    jrows = np.flatnonzero(junction)
    J = 3
    P = np.zeros((len(jrows), J))
    r = ring[jrows]
    P[r <= 2, 0] = 1.0 - 0.2 * r[r <= 2]
    P[r <= 2, 1] = 0.2 * r[r <= 2]
    alt = np.arange(len(V))[jrows] % 2 == 0
    P[(r > 2) & alt, 1] = 1.0
    P[(r > 2) & ~alt, 2] = 1.0
    d = np.where(r <= 2, 0.0, 1.0)
    owned = np.flatnonzero(ring == 0)
    known = [(owned, np.tile([1.0, 0.0, 0.0], (len(owned), 1)))]
    out = continue_far_parts(V, F, [P], [d], junction, known, near=0.5)[0]
    far = r > 2
    assert np.array_equal(out[~far], P[~far])  # near rows: the input's own painting, untouched
    # far rows continue ring 2 (0.6, 0.4, 0): one value per ring, no stripes, no jumping joint
    assert np.allclose(out[far], [0.6, 0.4, 0.0], atol=1e-9)
    # the same far rows, smooth (all joint 1): kept, whatever their distance
    smooth = P.copy()
    smooth[far] = [0.0, 1.0, 0.0]
    assert np.array_equal(continue_far_parts(V, F, [smooth], [d], junction, known, near=0.5)[0], smooth)
    # near everywhere: kept, stripes and all
    assert np.array_equal(continue_far_parts(V, F, [P], [np.zeros_like(d)], junction, known, near=0.5)[0], P)


@pytest.mark.parametrize("method", WEIGHT_METHODS)
def test_output_weights_past_the_dense_limit(method):
    """The same case on 2**24 // n + 1 output joints (the extra ones unused): the weights are per
    influence, so ``nearest`` (no fill) gives the same rows; the fill, dense over the surface,
    is refused by its declared limit with an error naming it."""
    surf, x, bm = _isolated_junction_case()
    n = len(surf.V)
    J = MAX_DENSE_WEIGHT_ENTRIES // n + 1
    params = WeightParams(method=method)
    if method == "nearest":
        small = blend_weights(surf, [x], [bm], 3, params=params)
        skin = blend_weights(surf, [x], [bm], J, params=params)
        assert sp.issparse(skin.W) and skin.W.shape == (n, J) and skin.W.nnz <= 4 * n
        assert skin.W[:, :3].toarray().tobytes() == small.W.toarray().tobytes() and skin.W[:, 3:].nnz == 0
    else:
        with pytest.raises(InputError, match=rf"weights: the junction fill .*{n} vertices x {J} joints.*limit"):
            blend_weights(surf, [x], [bm], J, params=params)


@pytest.mark.parametrize("method", WEIGHT_METHODS)
def test_junction_component_with_no_matched_vertex_gets_finite_normalized_weights(method):
    surf, x, bm = _isolated_junction_case()
    skin = blend_weights(surf, [x], [bm], 3, params=WeightParams(method=method))
    j = skin.junction
    assert j.sum() == len(surf.V) - len(x.V)
    assert not skin.matched[j].any()  # too far from every input: nothing matched
    assert sp.issparse(skin.W)
    W = skin.W.toarray()[j]
    assert np.all(np.isfinite(W)) and np.all(W >= 0)
    assert np.allclose(W.sum(axis=1), 1.0)
    assert np.all(np.count_nonzero(W > 0, axis=1) <= 4)
    # preserved rows are the input's, bit-identical
    assert skin.W.toarray()[~j].tobytes() == dense_rows(x.W).tobytes()


def test_geodesic_locality_keeps_weights_off_a_look_alike_part():
    """Two identical spheres, each driven by its own joint; the right sphere's cap is unknown.
    The filled cap must take the right sphere's joint only, never the left twin's."""
    from rigmix.weights.locality import geodesic_locality

    VA, F = _sphere(c=(-3.0, 0, 0))
    VB, _ = _sphere(c=(3.0, 0, 0))
    V = np.r_[VA, VB]
    FF = np.r_[F, F + len(VA)]
    W = np.zeros((len(V), 2))
    W[: len(VA), 0] = 1.0
    W[len(VA):, 1] = 1.0
    unknown = np.zeros(len(V), bool)
    unknown[len(VA):][VB[:, 1] > 0.5] = True
    leaked = W.copy()
    leaked[unknown] = [0.5, 0.5]  # a fill that borrowed from the look-alike
    out = geodesic_locality(V, FF, leaked, unknown, radius=1.5)
    assert np.allclose(out[unknown], [0.0, 1.0])
    assert np.array_equal(out[~unknown], W[~unknown])


def test_geodesic_locality_keeps_a_joint_its_trusted_prior_witnesses():
    """A sphere driven by two joints, top and bottom; joint 1's whole cap is unknown, so no known
    vertex witnesses it. The fill's joint 1 is cut, unless a trusted prior (the mirror image of
    a hidden limb) witnesses it on the cap; a joint nothing witnesses is still cut."""
    from rigmix.weights.locality import geodesic_locality, locality_radius

    V, F = _sphere()
    W = np.zeros((len(V), 3))
    W[V[:, 1] <= 0.3, 0] = 1.0
    W[V[:, 1] > 0.3, 1] = 1.0
    unknown = V[:, 1] > 0.3
    filled = W.copy()
    filled[unknown] = [0.2, 0.7, 0.1]  # joint 2: a leak nothing supports
    radius = locality_radius(V, F, unknown, 0.1)
    assert radius > 0.1  # raised to the band's reach
    cut = geodesic_locality(V, F, filled, unknown, radius=radius)
    assert np.all(cut[unknown, 1] == 0) and np.allclose(cut[unknown, 0], 1.0)
    witness = np.zeros_like(W)
    witness[unknown, 1] = 1.0
    kept = geodesic_locality(V, F, filled, unknown, radius=radius, witness=witness)
    assert np.all(kept[unknown, 1] > 0.7) and np.all(kept[unknown, 2] < 0.1)
    assert np.allclose(kept.sum(axis=1), 1.0) and np.array_equal(kept[~unknown], W[~unknown])


def test_geodesic_locality_keeps_a_hidden_joint_that_deforms_the_inputs():
    """A joint no vertex witnesses is cut: a root or an IK bone that deforms nothing. One of
    ``deforming_joints`` with no witness is one whose whole surface is unknown (a head inside a
    junction band): it keeps its filled weights; one with witnesses is still limited by them."""
    from rigmix.weights.locality import geodesic_locality, locality_radius

    V, F = _sphere()
    W = np.zeros((len(V), 3))
    W[:, 0] = 1.0
    unknown = V[:, 1] > 0.3
    filled = W.copy()
    filled[unknown] = [0.3, 0.6, 0.1]  # joint 1: the cap's own, from its bone; joint 2: a leak
    radius = locality_radius(V, F, unknown, 0.1)
    cut = geodesic_locality(V, F, filled, unknown, radius=radius)
    assert np.allclose(cut[unknown], [1.0, 0.0, 0.0])
    deforming = np.array([True, True, False])
    kept = geodesic_locality(V, F, filled, unknown, radius=radius, deforming_joints=deforming)
    assert np.all(kept[unknown, 2] == 0) and np.all(kept[unknown, 1] > 0.6)
    assert np.allclose(kept.sum(axis=1), 1.0) and np.array_equal(kept[~unknown], W[~unknown])
    # joint 0 is witnessed below the cap: it still fades with the distance from there
    assert np.all(np.diff(kept[unknown, 0][np.argsort(V[unknown, 1])]) <= 1e-12)


def test_to_influences_keeps_the_largest_four():
    W = np.array([[0.1, 0.2, 0.3, 0.4, 0.0], [1.0, 0, 0, 0, 0]])
    J, w = to_influences(W, 4)
    assert J.shape == (2, 4)
    assert np.allclose(w[0], [0.4, 0.3, 0.2, 0.1]) and list(J[0]) == [3, 2, 1, 0]
    assert list(J[1]) == [0, 0, 0, 0] and np.allclose(w[1], [1, 0, 0, 0])


# ------------------------------------------------------------------------------------------
# Every composition config: invariants (compositions cached per module)
# ------------------------------------------------------------------------------------------


def _check_invariants(comp):
    skin = comp.weights
    assert sp.issparse(skin.W)
    W = skin.W.toarray()
    assert np.all(np.isfinite(W)) and np.all(W >= 0)
    assert np.allclose(W.sum(axis=1), 1.0, atol=1e-12)
    assert np.count_nonzero(W > 0, axis=1).max() <= 4
    assert skin.report["junction_vertices"] == int(comp.surface.junction_vertices.sum())
    # every split copy of a position has the same weights: no seam opens under animation
    _, index, _ = weld(comp.surface.V, comp.surface.F)
    first = np.full(index.max() + 1, -1)
    first[index[::-1]] = np.arange(len(index))[::-1]
    assert np.abs(W - W[first[index]]).sum(axis=1).max() < 1e-12
    # preserved vertices copy their retargeted weights exactly (inputs with <= 4 influences): through
    # the bone map, or, where the weights were given the skeleton (as the pipeline gives it), with
    # the cut-off joints whose image is elsewhere sent to the nearest kept joint
    surf = comp.surface
    maps = [comp.maps[c] for c in comp.fusion_ids]
    J = comp.skeleton.num_joints
    plain = retarget_inputs(comp.fusion_inputs, maps, J)[0]
    cut = retarget_inputs(comp.fusion_inputs, maps, J, skeleton=comp.plan.skeleton,
                          cut_reach=WeightParams().cut_joint_reach)[0]
    for i in range(len(comp.fusion_inputs)):
        rows = np.flatnonzero((surf.origin_input == i) & ~surf.junction_vertices)
        copies = []
        for Wr in (plain[i].toarray(), cut[i].toarray()):
            small = np.count_nonzero(Wr[surf.origin_vertex[rows]] > 0, axis=1) <= 4
            copies.append(np.array_equal(W[rows[small]], Wr[surf.origin_vertex[rows[small]]]))
        assert any(copies), (i, copies)


@IN_COMPOSED_GROUP
@pytest.mark.parametrize("cfg", EXAMPLES, ids=lambda c: c.stem)
def test_every_example_config_weight_invariants_and_stretch_ratio_for_every_method(cfg, composed):
    """Composed once per config: W_R invariants (dfd), then every method's junction stretch ratio
    (acceptance 3 on the built-in examples: dfd <= 1.5) and junction weight roughness (dfd's
    seam no spikier than the paper's blend nor than 1.5x the inputs' painting; measured max
    dfd / nearest / inputs: beast_arms 0.17 / 0.83 / 0.14, centaur 0.19 / 0.49 / 0.14,
    tailed_humanoid 0.17 / 0.34 / 0.14)."""
    from rigmix.pipeline import assembly_stage, quality_stage

    comp = composed(cfg)
    _check_invariants(comp)
    ids = comp.fusion_ids
    ratios, roughness, source_roughness = {}, {}, None
    for method in WEIGHT_METHODS:
        skin = blend_weights(comp.surface, comp.fusion_inputs, [comp.maps[c] for c in ids],
                             comp.skeleton.num_joints, params=WeightParams(method=method))
        c = replace(comp, weights=skin)
        _check_invariants(c)
        q = quality_stage(assembly_stage(c)).report["quality"]
        ratios[method], roughness[method] = q["junction_stretch_ratio"], q["junction_weight_roughness_max"]
        source_roughness = q["source_weight_roughness_max"]  # the inputs' painting: the same for every method
    assert all(r is not None and np.isfinite(r) and r > 0 for r in ratios.values()), ratios
    assert roughness["dfd"] <= roughness["nearest"] + 1e-9, (cfg.stem, roughness)
    # and within 1.5x the inputs' own painting (beast_arms 0.29 against 0.14 before the far
    # inputs' jumping closest points were continued: striped armpits)
    assert roughness["dfd"] <= 1.5 * source_roughness, (cfg.stem, roughness, source_roughness)
    # every example, beast_arms included (3.4 before its replaced limb roots were completed
    # from the quadruped in the human's clips)
    assert ratios["dfd"] <= 1.5, (cfg.stem, ratios)


# ------------------------------------------------------------------------------------------
# Self-composition: the truth is known everywhere
# ------------------------------------------------------------------------------------------


def test_self_composition_against_the_original_weights():
    """CesiumMan's left arm (tests/configs/self_composition.toml, junction copied by default:
    nearest and dfd get the original's weights), the Fox's tail and RiggedFigure's left arm (junction
    rebuilt from the fields), replaced by themselves: invariants, dfd's weights equal to the
    original's (every junction vertex lies on the input surface; RiggedFigure's arm has remeshed
    vertices whose normals differ from the input's by over 90 degrees, which the on-surface
    match keeps from the fill: without it, mean error 0.007 and skinned 0.46%), dfd's mean
    junction weight error no worse than inpaint's. (dfd cannot be below nearest here: the truth
    at a new vertex is the original's weights at its closest original point, nearest's rule.)"""
    from benchmarks.self_composition import self_config
    from rigmix.pipeline import compose
    from rigmix.quality import self_composition_errors

    asset("CesiumMan")
    cesium = compose(ROOT / "tests" / "configs" / "self_composition.toml", until="weights")
    _check_invariants(cesium)
    rebuilt = {"copy_coincident": False}
    comps = {"CesiumMan arm": cesium,
             "Fox tail": compose(self_config(asset("Fox"), "b_Tail01_012", fusion=rebuilt), until="fusion"),
             "RiggedFigure arm": compose(self_config(asset("RiggedFigure"), "arm_joint_L_1", fusion=rebuilt),
                                         until="fusion")}
    assert cesium.surface.report["mesh"]["copied_faces"] > 0  # the default copies the shared junction
    for name in ("Fox tail", "RiggedFigure arm"):
        assert comps[name].surface.report["mesh"]["copied_faces"] == 0
    for name, comp in comps.items():
        ids = comp.fusion_ids
        figs = {}
        for method in WEIGHT_METHODS:
            skin = blend_weights(comp.surface, comp.fusion_inputs, [comp.maps[c] for c in ids],
                                 comp.skeleton.num_joints, params=WeightParams(method=method))
            figs[method] = self_composition_errors(comp, skin)
        assert figs["dfd"]["frames"] > 0 and figs["dfd"]["junction_vertices"] > 0
        assert figs["dfd"]["skinned_error_max"] < 1e-9 and figs["dfd"]["junction_weight_error_max"] < 1e-9, \
            (name, figs["dfd"])
        assert figs["dfd"]["junction_weight_error_mean"] <= figs["inpaint"]["junction_weight_error_mean"] + 1e-12, \
            (name, {m: f["junction_weight_error_mean"] for m, f in figs.items()})
        if name == "CesiumMan arm":  # copied vertices lie on both inputs: the closest points are exact
            f = figs["nearest"]
            assert f["junction_weight_error_max"] < 1e-9 and f["skinned_error_max"] < 1e-9, f


# ------------------------------------------------------------------------------------------
# Junction stretch ratio
# ------------------------------------------------------------------------------------------


def test_weight_roughness_finds_a_spike_and_welds_split_vertices():
    from rigmix.quality import weight_roughness

    V, F = _sphere(8, 10)

    def ring(u):
        n = np.unique(F[(F == u).any(axis=1)])
        return n[n != u]

    y = (V[:, 1] + 1) / 2
    W = np.c_[y, 1 - y, np.zeros(len(V))]  # a smooth transition, rough only by its curvature
    assert weight_roughness(V, F, W).max() < 0.15
    v = 40
    spiked = W.copy()
    spiked[v] = [0.0, 0.0, 1.0]  # a joint none of its neighbours has
    r = weight_roughness(V, F, spiked)
    expected = [0.5 * np.abs(spiked[u] - spiked[ring(u)].mean(axis=0)).sum() for u in range(len(V))]
    assert np.allclose(r, expected) and r[v] == pytest.approx(1.0)
    assert r[ring(v)].min() > 1 / len(ring(v)) - 0.2  # the spike shows on its ring too
    assert weight_roughness(V, F, spiked, rows=np.arange(len(V)) == v) == pytest.approx([1.0])
    # a seam through the spike (two of its faces on a copy of it): the copies are one vertex
    Fs = F.copy()
    faces = np.flatnonzero((F == v).any(axis=1))[:2]
    Fs[faces] = np.where(F[faces] == v, len(V), F[faces])
    assert np.allclose(weight_roughness(np.r_[V, V[[v]]], Fs, np.r_[spiked, spiked[[v]]]), r)


def test_face_stretch_matches_the_svd_reference_and_is_zero_for_rigid_motion():
    from rigmix.quality import face_stretch

    rng = np.random.default_rng(1)
    V, F = _sphere(6, 8)
    A = rng.normal(size=(3, 3))
    U = (V @ A.T)[None]

    def frame(P, f):
        e1, e2 = P[f[1]] - P[f[0]], P[f[2]] - P[f[0]]
        n = np.cross(e1, e2)
        return np.stack([e1, e2, n / np.linalg.norm(n)], axis=1)

    ref = [np.linalg.norm(np.log(np.linalg.svd(frame(U[0], f) @ np.linalg.inv(frame(V, f)), compute_uv=False)))
           for f in F]
    assert np.allclose(face_stretch(V, U, F)[0], ref, atol=1e-9)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    assert np.abs(face_stretch(V, (V @ R.T + 2.0)[None], F)).max() < 1e-6


# ------------------------------------------------------------------------------------------
# The DFD feature field in the default dfd
# ------------------------------------------------------------------------------------------


def test_dfd_with_feature_field_distills_the_field_of_the_fused_surface(tmp_path):
    """dfd with ``feature_field=True`` distills a field on the fused surface (with
    :data:`FIELD_DISTILL`) and the field changes the filled weights; the default distills nothing."""
    from dfd.field import load_field
    from rigmix.config import PositioningOptions, load_config
    from rigmix.pipeline import compose
    from rigmix.weights.blend import FIELD_DISTILL

    asset("Horse"), asset("Knight")
    # the stored rest pose, where the centaur's junction has rows to fill
    config = load_config(ROOT / "tests" / "configs" / "centaur.toml")
    comp = compose(config.model_copy(update={"positioning": PositioningOptions(pose="rest")}), until="fusion")
    ids = comp.fusion_ids
    args = (comp.surface, comp.fusion_inputs, [comp.maps[c] for c in ids],
            comp.skeleton.num_joints)
    off = blend_weights(*args, params=WeightParams(method="dfd", field_cache=tmp_path / "off"))
    assert not (tmp_path / "off").exists() and off.report["feature_field"] is False
    on = blend_weights(*args, params=WeightParams(method="dfd", feature_field=True, field_cache=tmp_path / "on"))
    assert on.report["feature_field"] is True and on.report["feature_field_distilled"] is True
    assert on.report["feature_field_s"] > 0 and off.report["feature_field_distilled"] is False
    fields = sorted((tmp_path / "on").glob("field-*.pt"))
    assert len(fields) == 1
    field = load_field(fields[0])
    for key, value in FIELD_DISTILL.items():
        assert field.settings[key] == value
    # the field is the fused surface's: the welded junction and preserved vertices, unit features
    f = field.evaluate(comp.surface.V[:100])
    assert np.allclose(np.linalg.norm(f, axis=1), 1.0, atol=1e-5)
    on, off = (replace(s, W=s.W.toarray()) for s in (on, off))
    for skin in (on, off):
        W = skin.W
        assert np.all(W >= 0) and np.allclose(W.sum(axis=1), 1.0) and np.count_nonzero(W, axis=1).max() <= 4
    # preserved rows are the inputs' either way; the field moves some junction rows
    assert np.array_equal(on.junction, off.junction)
    assert np.array_equal(on.W[~on.junction], off.W[~off.junction])
    assert np.abs(on.W - off.W).sum(axis=1).max() > 1e-6


def test_cli_feature_field_options(tmp_path):
    """``rigmix compose --feature-field`` / ``--no-feature-field`` reach the weight stage; the
    default is without the field."""
    import json

    from rigmix.cli import main

    asset("CesiumMan"), asset("Velociraptor")
    cfg = ROOT / "tests" / "configs" / "tail_graft.toml"
    for k, (extra, expected) in enumerate((([], False), (["--feature-field"], True), (["--no-feature-field"], False))):
        report = tmp_path / f"report{k}.json"
        assert main(["compose", str(cfg), "-o", str(tmp_path / "out.glb"), "--report", str(report),
                     "--no-progress", *extra]) == 0
        weights = json.loads(report.read_text())["weights"]
        assert weights["method"] == "dfd" and weights["feature_field"] is expected
        # every tail junction vertex is matched (nothing filled): no field is distilled either way
        assert weights["matched_vertices"] == weights["junction_vertices"] > 0
        assert weights["feature_field_distilled"] is False and weights["feature_field_s"] == 0.0


def test_mirrored_limb_harmonic_blend_keeps_the_artists_weights():
    """The Velociraptor's left leg replaced by its mirrored right leg: the truth is the original
    everywhere the mirrored leg lies on it. The paper's blend factors jump between the two
    paintings (mean junction weight error 0.034, skinned 2.3% of the diagonal); dfd's harmonic
    blend factors ramp across the junction and land within 0.005 and 0.5%. Also: every method
    keeps the invariants, and ``blend = "paper"`` is the paper's rule under dfd too."""
    from benchmarks.self_composition import LIMBS, mirror_case, mirrored_errors

    limbs = LIMBS["Velociraptor"]
    # in the file's stored rest pose, where the two paintings differ across the junction
    comp, pair, _, _ = mirror_case(asset("Velociraptor"), limbs["leg.L"], limbs["leg.R"], until="fusion",
                                   pose="rest")
    ids = comp.fusion_ids
    figs, skins = {}, {}
    for label, opts in {"nearest": {"method": "nearest"}, "dfd": {"method": "dfd"},
                        "dfd_paper": {"method": "dfd", "blend": "paper", "feature_field": False}}.items():
        skins[label] = blend_weights(comp.surface, comp.fusion_inputs,
                                     [comp.maps[c] for c in ids], comp.skeleton.num_joints, params=WeightParams(**opts))
        figs[label] = mirrored_errors(comp, skins[label], pair, max_frames=60)
        _check_invariants(replace(comp, weights=skins[label]))
    assert skins["dfd"].report["blend"] == "harmonic" and skins["nearest"].report["blend"] == "paper"
    err = {k: f["junction_weight_error_mean"] for k, f in figs.items()}
    assert figs["dfd"]["measured_vertices"] > 50
    assert err["dfd"] < 0.005 and err["nearest"] > 0.02 and err["dfd_paper"] > 0.02, err
    assert figs["dfd"]["skinned_error_max"] < 0.005 < figs["nearest"]["skinned_error_max"], figs
    with pytest.raises(InputError, match="unknown blend"):
        blend_weights(comp.surface, comp.fusion_inputs, [comp.maps[c] for c in ids],
                      comp.skeleton.num_joints, params=WeightParams(method="dfd", blend="smooth"))


def test_mirrored_truth_only_where_the_junction_faces_the_original_surface():
    """The Knight's rest pose is not symmetric: its left arm replaced by the mirrored right arm puts
    the donor's thumb into the left thigh, and junction vertices on the thumb lie within a voxel
    of the thigh, facing it. The thigh's weights are no truth for them (every method scored about
    59% of the diagonal against them); measured only where the vertex faces the same way as the
    original surface, the closest-point rule is within 2%."""
    from benchmarks.self_composition import LIMBS, mirror_case, mirrored_errors

    limbs = LIMBS["Knight"]
    comp, pair, _, _ = mirror_case(asset("Knight"), limbs["arm.L"], limbs["arm.R"], until="fusion",
                                   pose="rest")  # the stored rest pose, thumb against the thigh
    ids = comp.fusion_ids
    skin = blend_weights(comp.surface, comp.fusion_inputs, [comp.maps[c] for c in ids],
                         comp.skeleton.num_joints, params=WeightParams(method="nearest"))
    figs = mirrored_errors(comp, skin, pair, max_frames=20)
    assert 0.9 * figs["junction_vertices"] < figs["measured_vertices"] < figs["junction_vertices"], figs
    assert figs["skinned_error_max"] < 0.02 and figs["junction_weight_error_max"] < 1.0, figs


@pytest.mark.parametrize("name, joint, dfd_bound", [("CesiumMan", "leg_joint_L_1", 0.1),
                                                     ("Fox", "b_LeftUpperArm_09", 0.3)])
def test_hidden_junction_is_filled_best_by_dfd(name, joint, dfd_bound):
    """A limb replaced by itself with the junction rebuilt and every junction row hidden (the
    benchmark's ``hidden`` protocol): each method fills the whole band from the preserved
    vertices alone, against a known truth. Measured mean junction weight error (nearest /
    inpaint / dfd): CesiumMan's left leg 0.78 / 0.20 / 0.05, the Fox's left front leg (its upper
    arm joint hidden all over the band: only the mirror prior witnesses it, which the geodesic
    locality must keep) 1.18 / 1.04 / 0.18. The dfd measured is the default one, without a
    feature field (``benchmarks/results/self_composition.md``: 0.018 and 0.182 without it, 0.018
    and 0.184 with it); the field's own case is
    :func:`test_hidden_junction_with_a_field_that_tells_the_sides_apart`."""
    from benchmarks.self_composition import METHODS, REBUILT, hidden_weights, self_config
    from rigmix.pipeline import compose
    from rigmix.quality import self_composition_errors

    comp = compose(self_config(asset(name), joint, fusion=REBUILT), until="fusion")
    figs = {}
    for label, options in METHODS:
        if options.get("feature_field"):
            continue
        skin, _ = hidden_weights(comp, options)
        assert skin.report["matched_vertices"] == 0 and not skin.matched.any()
        _check_invariants(replace(comp, weights=skin))
        figs[label] = self_composition_errors(comp, skin, max_frames=30)
    assert figs["dfd_no_field"]["junction_vertices"] > 100
    err = {k: f["junction_weight_error_mean"] for k, f in figs.items()}
    skinned = {k: f["skinned_error_max"] for k, f in figs.items()}
    assert err["dfd_no_field"] < dfd_bound < err["inpaint"] < err["nearest"], err
    assert skinned["dfd_no_field"] < skinned["inpaint"] < skinned["nearest"], skinned


@pytest.mark.parametrize("joint", ["BackUpLeg.L", "BackUpLeg.R"])
def test_hidden_junction_of_a_limb_posed_asymmetrically(joint):
    """The shared Velociraptor's rest pose steps forward with its left foot. Hidden protocol on
    its legs: the mirror prior must come from the body's plane (x = 0) with the feet paired by
    name (on the plane of least mean error, tilted 6 degrees, the left leg scored 0.87 against
    inpaint's 0.77, skinned 34% of the diagonal), and each hip's reflection, which lands in the
    air, must follow its bone onto the other leg's (posed reflection): without it, mean junction
    weight error 0.46 (left) and 0.58 (right) against inpaint's 0.77 and 0.80; now 0.26 and 0.25,
    skinned 5% and 9%."""
    from benchmarks.self_composition import REBUILT, hidden_weights, self_config
    from rigmix.pipeline import compose
    from rigmix.quality import self_composition_errors

    comp = compose(self_config(asset("Velociraptor"), joint, fusion=REBUILT), until="fusion")
    figs = {}
    for method in ("inpaint", "dfd"):
        skin, _ = hidden_weights(comp, {"method": method})
        _check_invariants(replace(comp, weights=skin))
        figs[method] = self_composition_errors(comp, skin, max_frames=20)
    err = {k: f["junction_weight_error_mean"] for k, f in figs.items()}
    assert err["dfd"] < 0.4 * err["inpaint"], err
    assert figs["dfd"]["skinned_error_max"] < 0.12, figs["dfd"]


def test_posed_reflection_follows_the_bones_of_the_surface_around():
    """The shared Knight's right thumb touches its thigh: in space, the thigh is the bone closest
    to the thumb's hidden vertices, and a reflection following it landed on the other thigh
    (UpperLeg.R on the thumb, skinned error 52% of the diagonal, hidden protocol on the right
    arm). A point follows the bones of the joints that weight the known surface nearest to it
    along the surface: a few % (3.4% before the crossing repair and unit-scale skeletons moved
    the junction, 6.2% since), far from the wrong bone's 52%."""
    from benchmarks.self_composition import REBUILT, hidden_weights, self_config
    from rigmix.pipeline import compose
    from rigmix.quality import self_composition_errors

    # the stored rest pose, where the thumb touches the thigh
    comp = compose(self_config(asset("Knight"), "UpperArm.R", fusion=REBUILT, pose="rest"), until="fusion")
    skin, _ = hidden_weights(comp, {"method": "dfd", "feature_field": False})
    figs = self_composition_errors(comp, skin, max_frames=20)
    assert figs["junction_weight_error_mean"] < 0.2 and figs["skinned_error_max"] < 0.1, figs


def test_hidden_junction_with_a_field_that_tells_the_sides_apart():
    """The shared Knight's distilled field differs between its two sides by a median feature
    distance of 0.17 on the known surface, as much as between the right leg's hidden band and
    its mirror (0.15). Judged by the raw distance, the field cut the trust of correct mirror
    rows below the locality's witness threshold: hidden protocol on the right leg, mean junction
    weight error 0.25 and skinned 9.9% of the diagonal with the field against 0.10 and 4.0%
    without it. The mirror prior now only counts what exceeds the field's own difference between
    the sides: 0.09 and 4.0%."""
    from benchmarks.self_composition import REBUILT, hidden_weights, self_config
    from rigmix.pipeline import compose
    from rigmix.quality import self_composition_errors

    comp = compose(self_config(asset("Knight"), "UpperLeg.R", fusion=REBUILT), until="fusion")
    figs = {}
    for label, options in (("field", {"feature_field": True}), ("no_field", {"feature_field": False})):
        skin, _ = hidden_weights(comp, {"method": "dfd", **options})
        figs[label] = self_composition_errors(comp, skin, max_frames=20)
    assert skin.report["feature_field"] is False
    err = {k: f["junction_weight_error_mean"] for k, f in figs.items()}
    assert err["field"] < 0.15 and err["field"] <= 1.1 * err["no_field"], err
    assert figs["field"]["skinned_error_max"] < 0.06, figs["field"]


def test_hidden_junction_of_a_coarse_character_mirrors_across_its_body_plane():
    """The shared RiggedFigure is coarse: with a leg's junction band remeshed, the band holds 72%
    of the welded vertices. Judged by vertex-to-vertex reflection, the symmetry plane was the
    front/back one; the mirror prior then read the torso and the arms, and the geodesic locality
    dropped the hidden thigh joints (hidden protocol, mean junction weight error 1.22 on the left
    leg, 1.20 on the right, against inpaint's 1.45 and 1.44). Judged on the surface, the plane is
    x = 0 and the prior reads the other leg: 0.07."""
    from benchmarks.self_composition import REBUILT, hidden_weights, self_config
    from rigmix.pipeline import compose
    from rigmix.quality import self_composition_errors
    from rigmix.weights.mesh import welded_mesh

    for joint in ("leg_joint_L_1", "leg_joint_R_1"):
        comp = compose(self_config(asset("RiggedFigure"), joint, fusion=REBUILT), until="fusion")
        surface = comp.surface
        g = welded_mesh(surface.V, surface.F)
        plane = symmetry_plane(g.V, g.F)
        assert plane is not None and abs(plane.normal[0]) > 1 - 1e-9, (joint, plane)
        figs = {}
        for method, options in (("inpaint", {}), ("dfd", {"feature_field": False})):
            skin, _ = hidden_weights(comp, {"method": method, **options})
            _check_invariants(replace(comp, weights=skin))
            figs[method] = self_composition_errors(comp, skin, max_frames=20)
        err = {k: f["junction_weight_error_mean"] for k, f in figs.items()}
        assert err["dfd"] < 0.15 and err["dfd"] < 0.2 * err["inpaint"], (joint, err)
        assert figs["dfd"]["skinned_error_max"] < 0.005, (joint, figs["dfd"])


def test_hidden_junction_that_swallows_a_whole_part_keeps_its_joint():
    """The shared RiggedFigure is coarse: with its head replaced by itself, the junction band
    covers the whole head, so no known vertex carries the head joint (``neck_joint_2``). The
    locality removed it (hidden protocol: mean junction weight error 1.18, the head following
    the neck); a joint that deforms the inputs keeps what the fill gives it: 0.49. The Knight's
    root ``Bone`` deforms nothing and stays out of its right hip's band (kept, 11% of the band's
    weight and skinned error 19% of the diagonal)."""
    from benchmarks.self_composition import REBUILT, hidden_weights, self_config
    from rigmix.pipeline import compose
    from rigmix.quality import self_composition_errors, self_composition_truth

    comp = compose(self_config(asset("RiggedFigure"), "neck_joint_1", fusion=REBUILT), until="fusion")
    junction = np.asarray(comp.surface.junction_vertices, bool)
    head = comp.skeleton.index("neck_joint_2")
    truth = self_composition_truth(comp)[junction, head].sum()
    figs = {}
    for method in ("inpaint", "dfd"):
        skin, _ = hidden_weights(comp, {"method": method, "feature_field": False} if method == "dfd"
                                 else {"method": method})
        figs[method] = self_composition_errors(comp, skin, max_frames=20)
    assert truth > 0.3 * junction.sum() and skin.W.toarray()[junction, head].sum() > 0.5 * truth
    err = {k: f["junction_weight_error_mean"] for k, f in figs.items()}
    assert err["dfd"] < 0.7 and err["dfd"] < 0.5 * err["inpaint"], err
    assert figs["dfd"]["skinned_error_max"] < figs["inpaint"]["skinned_error_max"], figs

    comp = compose(self_config(asset("Knight"), "UpperLeg.R", fusion=REBUILT), until="fusion")
    junction = np.asarray(comp.surface.junction_vertices, bool)
    skin, _ = hidden_weights(comp, {"method": "dfd", "feature_field": False})
    assert not skin.W.toarray()[junction, comp.skeleton.index("Bone")].any()


def test_hidden_junction_smoothed_only_where_no_prior_is_trusted():
    """Where no prior is trusted, the dfd fill is the inpainting and gets the robust transfer
    paper's post-smoothing (10 iterations of ``w <- 0.8 w + 0.2 mean(neighbours)``); a row the
    mirror prior decides keeps the painting it borrowed. Hidden protocol: the Knight's left
    shoulder within 5% of the diagonal (2.7% smoothed, 2.3% unsmoothed on the fold-free
    junction; 3.6% and 8.1% on a junction with folds); the Horse's front leg, which its mirror
    fills almost exactly, 0.005 mean junction weight error (smoothing every row: 0.067)."""
    from benchmarks.self_composition import REBUILT, hidden_weights, self_config
    from rigmix.pipeline import compose
    from rigmix.quality import self_composition_errors

    comp = compose(self_config(asset("Knight"), "UpperArm.L", fusion=REBUILT, pose="rest"), until="fusion")
    figs = {}
    for label, options in (("smoothed", {}), ("unsmoothed", {"iterations": 0})):
        skin, _ = hidden_weights(comp, {"method": "dfd", "feature_field": False, **options})
        figs[label] = self_composition_errors(comp, skin, max_frames=20)
    assert figs["smoothed"]["skinned_error_max"] < 0.05, figs
    assert figs["smoothed"]["junction_weight_error_mean"] < 0.16, figs

    comp = compose(self_config(asset("Horse"), "FrontUpperLeg.L", fusion=REBUILT, pose="rest"), until="fusion")
    skin, _ = hidden_weights(comp, {"method": "dfd", "feature_field": False})
    figs = self_composition_errors(comp, skin, max_frames=20)
    assert figs["junction_weight_error_mean"] < 0.01 and figs["skinned_error_max"] < 0.005, figs


def test_split_copies_of_a_position_get_the_same_weights():
    """Two triangles sharing an edge, each with its own copies of the edge's vertices (a glTF
    seam). A junction copy takes the preserved copy's row (never the reverse); two junction
    copies take their mean, cut to the influence limit."""
    from rigmix.weights.blend import weld_consistent

    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    F = np.array([[0, 1, 2], [3, 5, 4]])
    W = np.zeros((6, 6))
    W[0, 0] = W[5, 5] = 1.0
    W[1, [0, 1]] = 0.5          # preserved copy of (1, 0, 0)
    W[3, [2, 3]] = 0.5          # junction copy of (1, 0, 0)
    W[2, [0, 1, 2, 3]] = 0.25   # junction copies of (0, 1, 0)
    W[4, [1, 2, 3, 4, 5]] = 0.2
    junction = np.array([False, False, True, True, True, True])
    out, changed = weld_consistent(V, F, W, junction, max_influences=4)
    assert np.array_equal(out[:2], W[:2])                   # preserved rows untouched
    assert np.array_equal(out[3], W[1])                     # the junction copy takes the preserved row
    assert np.array_equal(out[2], out[4])                   # junction copies agree
    assert np.count_nonzero(out[2]) <= 4 and np.isclose(out[2].sum(), 1.0)
    mean = (W[2] + W[4]) / 2
    assert set(np.flatnonzero(out[2])) == set(np.argsort(-mean, kind="stable")[:4])
    assert np.array_equal(out[5], W[5]) and changed == 3
