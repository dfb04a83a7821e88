"""Fusion on the shared characters: self-composition has a known answer (PIPELINE.md section 7).

A character's limb replaced by the same limb of the same character must give back the
character. By default the junction's faces, which both inputs share, are copied as they are
(:func:`rigmix.fusion.seams.coincident_faces`): every face comes back bit-identical. With
``copy_coincident=False`` the junction is rebuilt from the blended fields as between two
different characters, which is what most of these tests exercise: surface within 0.5% of the
bounding-box diagonal (Hausdorff, both ways), at least 90% of the faces preserved exactly
(positions, UVs, normals bit-identical), no gap, no new non-manifold edge, good junction
triangles.
"""

from dataclasses import replace

import numpy as np
import pytest
from conftest import asset

from rigmix.fusion import FusionAction, FusionParams, fuse_surfaces
from rigmix.fusion.inputs import fusion_input
from rigmix.fusion.presence import raw_presence
from rigmix.geometry import bounding_box_diagonal

CASES = {
    "CesiumMan": "Skeleton_arm_joint_R",
    "Fox": "b_Neck_04",           # flat-shaded: every face split, centimetre-like units
    "Horse": "Tail1",             # low-poly tail root: long seam edges beside the junction
    "Wasp": "Abdomen",            # 13 parts after welding, NaN weights repaired on load
}


def _limb_self_composition(name, joint):
    """The two fusion inputs of ``name``'s subtree at ``joint`` replaced by itself: (rest, limb)."""
    from rigmix.io import load_character

    c = load_character(asset(name))
    sub = c.skeleton.subtree(c.skeleton.index(joint))
    return fusion_input(c, ~sub), fusion_input(c, sub)


def _hausdorff(a, out):
    """Two-sided Hausdorff distance between input ``a`` and the fused surface, over vertices,
    as a fraction of ``a``'s bounding-box diagonal."""
    import igl

    d_out = np.sqrt(igl.point_mesh_squared_distance(out.V, a.V, a.F)[0]).max()
    d_in = np.sqrt(igl.point_mesh_squared_distance(a.V, out.V, out.F)[0]).max()
    return max(d_out, d_in) / bounding_box_diagonal(a.V)


# the junction rebuilt from the fields, as between two different characters
REMESHED = FusionParams(copy_coincident=False)


@pytest.fixture(scope="module", params=sorted(CASES))
def self_composition(request):
    name = request.param
    a, b = _limb_self_composition(name, CASES[name])
    out = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)], params=REMESHED)
    return name, a, b, out


@pytest.mark.parametrize("name", sorted(CASES))
def test_self_composition_copies_the_shared_junction(name):
    """Default fusion of a limb replaced by itself: the junction faces lie on both inputs, so
    they are copied, each once, and the output is the input face for face (Hausdorff 0), with
    no generated triangle, and junction vertices only where no preserved face keeps the
    position."""
    from rigmix.fusion.report import mesh_report

    a, b = _limb_self_composition(name, CASES[name])
    out = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)])
    m = out.report["mesh"]
    assert m["copied_faces"] > 0 and m["junction_faces"] == m["copied_faces"]
    assert m["junction_min_angle_p05"] is None  # no generated triangle to measure
    assert np.all(out.face_origin_input >= 0)
    assert out.report["fields"]["voxels"] == 0  # no field was needed
    # the same faces, corner for corner, as the input (as multisets of position triples)
    def canon(P):
        return np.unique(P.reshape(len(P), 9), axis=0, return_counts=True)

    got, want = canon(out.V[out.F]), canon(a.V[a.F])
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert _hausdorff(a, out) == 0.0
    for k, x in enumerate((a, b)):
        faces = out.face_origin_input == k
        assert np.array_equal(out.V[out.F[faces]], x.V[x.F[out.face_origin_face[faces]]])
        verts = out.origin_input == k
        if x.uvs is not None:
            assert np.array_equal(out.uvs[verts], x.uvs[out.origin_vertex[verts]])
    before = mesh_report(a.V, a.F, np.zeros(len(a.F), bool), [])
    assert m["junction_boundary_edges"] == 0 and m["new_non_manifold_edges"] == 0
    assert m["boundary_edges"] == before["boundary_edges"]
    # vertices of copied faces get junction weights unless a preserved face shares the position
    jv = out.junction_vertices
    assert jv.any() and not np.any(jv & ~np.isin(np.arange(len(out.V)), out.F[out.copied_faces]))
    on_kept = np.zeros(len(out.V), bool)
    on_kept[out.F[~out.copied_faces].ravel()] = True
    assert not np.any(jv[out.origin_input >= 0] & on_kept[out.origin_input >= 0])


def test_a_partly_shared_junction_is_remeshed():
    """The donor arm inflated where its presence exceeds 0.6: the junction faces nearer the
    body are still shared, the rest are not. Joining copied faces to an isosurface would need
    seam loops that run along both inputs, so the whole junction is rebuilt from the fields,
    closed and clean. So is a donor moved by a billionth of its size."""
    from dataclasses import replace as dc_replace

    from rigmix.io import load_character

    c = load_character(asset("CesiumMan"))
    joint = "leg_joint_L_1"
    sub = c.skeleton.subtree(c.skeleton.index(joint))
    a, b = fusion_input(c, ~sub), fusion_input(c, sub)
    root = c.skeleton.rest_worlds()[c.skeleton.index(joint)][:3, 3]
    p = raw_presence(b.W, b.used)
    m = p > 0.6
    V = b.V.copy()
    V[m] = root + (V[m] - root) * (1.0 + 0.2 * (p[m] - 0.6))[:, None]
    out = fuse_surfaces([a, dc_replace(b, V=V)], [FusionAction("replace", 0, 1)])
    rep = out.report["mesh"]
    assert rep["copied_faces"] == 0 and rep["junction_faces"] > 0
    assert rep["junction_boundary_edges"] == 0 and rep["new_non_manifold_edges"] == 0
    assert rep["boundary_edges"] == 0 and rep["unmatched_loops"] == 0
    assert rep["junction_min_angle_p05"] >= 20
    # the unmoved shared faces alone would have been copied: the limb is what differs
    same = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)])
    assert same.report["mesh"]["copied_faces"] > 0
    # nearly the same faces are not the same: copies of both would not weld into one surface
    nudged = fuse_surfaces([a, dc_replace(b, V=b.V + 1e-9 * bounding_box_diagonal(b.V))],
                           [FusionAction("replace", 0, 1)])
    rep = nudged.report["mesh"]
    assert rep["copied_faces"] == 0 and rep["junction_boundary_edges"] == 0 and rep["boundary_edges"] == 0


def test_self_composition_is_closed_and_clean(self_composition):
    from rigmix.fusion.report import mesh_report

    name, a, b, out = self_composition
    m = out.report["mesh"]
    before = mesh_report(a.V, a.F, np.zeros(len(a.F), bool), [])
    assert m["junction_boundary_edges"] == 0
    assert m["boundary_edges"] == before["boundary_edges"]  # watertight where the input was
    assert m["new_non_manifold_edges"] == 0
    assert m["junction_faces"] > 0
    assert m["junction_min_angle_p05"] >= 20.0
    assert out.report["fields"]["voxels"] > 1000
    assert out.report["fields"]["backend"] == "numpy-igl"


def test_self_composition_reproduces_the_surface(self_composition):
    """Within 0.5% of the diagonal, and no further than the crossing repair moved a vertex
    beyond that (the Wasp's parts poking through its coarse junction are cleared by about a
    junction edge)."""
    name, a, _, out = self_composition
    moved = out.report["mesh"]["junction_repair_largest_move"] / bounding_box_diagonal(a.V)
    assert _hausdorff(a, out) <= 0.005 + moved, name
    kept = out.face_origin_input >= 0
    assert kept.sum() >= 0.9 * len(a.F)


def test_preserved_faces_are_bit_identical(self_composition):
    _, a, b, out = self_composition
    for k, x in enumerate((a, b)):
        faces = (out.face_origin_input == k) & ~out.junction_faces
        src = out.face_origin_face[faces]
        assert np.array_equal(out.V[out.F[faces]], x.V[x.F[src]])
        verts = out.origin_input == k
        sv = out.origin_vertex[verts]
        assert np.array_equal(out.V[verts], x.V[sv])
        if x.uvs is not None:
            assert np.array_equal(out.uvs[verts], x.uvs[sv])
        if x.normals is not None:
            assert np.array_equal(out.normals[verts], x.normals[sv])
        assert np.array_equal(out.mesh_of_vertex[verts], x.mesh_of_vertex[sv])
    # each input face is used at most once, and the two inputs never both keep a face
    fa = out.face_origin_face[(out.face_origin_input == 0)]
    fb = out.face_origin_face[(out.face_origin_input == 1)]
    assert len(np.unique(fa)) == len(fa) and len(np.unique(fb)) == len(fb)
    assert len(np.intersect1d(fa, fb)) == 0


def test_secondary_parts_are_kept_whole():
    from rigmix.io import load_character

    c = load_character(asset("Wasp"))
    sub = c.skeleton.subtree(c.skeleton.index("Abdomen"))
    from rigmix.fusion.presence import compute_presence

    a = fusion_input(c, ~sub)
    P = compute_presence(a.V, a.F, a.W, a.used)
    assert (P.component_decision == -1).sum() == 1        # the body is blended
    assert (P.component_decision >= 0).sum() == 12        # legs, wings, eyes...: never blended
    assert np.all(P.preserved[P.secondary] | P.absent[P.secondary])


def test_fidelity_refinement_recovers_what_remeshing_chords_off():
    """CesiumMan's left leg: remeshing to the neighbouring edge length alone leaves the surface
    0.57% of the diagonal from the original; refined against the isosurface it is within 0.5%,
    with the junction still closed and its triangles still good. Its second bridge recut would
    leave a non-manifold junction that cannot be remeshed: it is refused."""
    a, b = _limb_self_composition("CesiumMan", "leg_joint_L_1")

    plain = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)],
                          params=FusionParams(copy_coincident=False, fidelity_voxels=0))
    refined = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)],
                            params=replace(REMESHED, fold_free_deviation=0))
    assert _hausdorff(a, plain) > 0.005
    assert _hausdorff(a, refined) <= 0.005
    grid = refined.report["fields"]["grids"][0]
    assert grid["fidelity"] is True and grid["remeshed"] is True
    assert grid["bridge_recuts_rejected"] == 1 and grid["self_intersections"] == 0
    m = refined.report["mesh"]
    assert m["junction_self_intersections"] == 0
    assert m["junction_boundary_edges"] == 0 and m["new_non_manifold_edges"] == 0
    assert m["junction_min_angle_p05"] >= 20.0


def test_a_refined_junction_keeps_the_shape_without_folding():
    """CesiumMan's left leg: the shape-keeping junction is refined where the remeshing chords off
    the leg (:func:`rigmix.fusion.remesh.refine_where_stray`) before any vertex is kept. Pinning
    those vertices in the remeshing instead left each of them three faces, folded back past 150
    degrees, and the fusion fell back to the plain junction, 0.57% of the diagonal off: the
    refined one has no fold, no crossing, and stays within 0.5%."""
    from rigmix.fusion.meshutil import dihedral_angles
    from rigmix.fusion.stitch import FOLD_ANGLE

    a, b = _limb_self_composition("CesiumMan", "leg_joint_L_1")
    out = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)], params=REMESHED)
    grid = out.report["fields"]["grids"][0]
    assert grid["fidelity"] is True and "folds_avoided" not in grid
    junction = out.junction_faces & ~out.copied_faces
    assert np.count_nonzero(dihedral_angles(out.V, out.F, junction) > FOLD_ANGLE) == 0
    assert out.report["mesh"]["junction_self_intersections"] == 0
    assert _hausdorff(a, out) <= 0.005


def test_a_folded_refinement_gives_way_to_the_plain_junction():
    """RiggedFigure's left leg (a box figure): the shape-keeping junction keeps vertices at box
    corners, and triangles between them fold back (neighbours turned past 150 degrees). The
    plain junction strays several times farther from the isosurface, more than the default
    ``fold_free_deviation`` allows; with a larger allowance the fusion takes it, and it folds
    nowhere."""
    from rigmix.fusion.meshutil import dihedral_angles
    from rigmix.fusion.stitch import FOLD_ANGLE

    a, b = _limb_self_composition("RiggedFigure", "leg_joint_L_1")
    kept = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)], params=REMESHED)
    out = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)], params=replace(REMESHED, fold_free_deviation=10.0))

    def folds(x):
        return np.count_nonzero(dihedral_angles(x.V, x.F, x.junction_faces & ~x.copied_faces) > FOLD_ANGLE)

    assert kept.report["fields"]["grids"][0]["fidelity"] is True and folds(kept) > 0
    grid = out.report["fields"]["grids"][0]
    assert grid["folds_avoided"] > 0 and grid["fidelity"] is False
    assert folds(out) == 0
    assert out.report["mesh"]["junction_self_intersections"] == 0


def test_collapses_let_the_junction_keep_the_shape_of_a_low_poly_tail():
    """The Horse's tail root: its preserved faces leave seam edges up to five target edges long,
    and the remeshed strip beside them is flat caps (p05 of the minimum angle 19 degrees with
    the shape kept). Without collapsing the crowded vertices the fusion falls back to the
    plain remeshing and its rounded-off root, 1.3% of the diagonal from the original; with
    them it keeps the shape and the triangles."""
    a, b = _limb_self_composition("Horse", "Tail1")

    without = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)],
                            params=FusionParams(copy_coincident=False, collapse_poor=False))
    out = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)], params=REMESHED)
    assert without.report["fields"]["grids"][0]["fidelity"] is False
    assert _hausdorff(a, without) > 0.005
    assert out.report["fields"]["grids"][0]["fidelity"] is True
    assert _hausdorff(a, out) <= 0.005
    assert out.report["mesh"]["junction_min_angle_p05"] >= 20.0


def test_a_looser_fidelity_tolerance_is_tried_before_none():
    """RiggedFigure's right arm (a box figure, faces 7% of the diagonal), its junction not
    refined and not held to the inputs' creases (``refine_rounds = 0``, ``crease_ratio = 0``): at
    the default tolerance the shape-keeping junction misses 20 degrees at p05; without a looser
    try the fusion falls back to the plain remeshing, 2.2% of the diagonal off at a box corner.
    Four times the tolerance keeps the corners and the triangles. Refined, the default
    tolerance does."""
    a, b = _limb_self_composition("RiggedFigure", "arm_joint_R_1")

    unrefined = replace(REMESHED, refine_rounds=0, crease_ratio=0.0)
    strict = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)], params=replace(unrefined, fidelity_relax=()))
    out = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)], params=unrefined)
    assert strict.report["fields"]["grids"][0]["fidelity"] is False
    assert _hausdorff(a, strict) > 0.005
    grid = out.report["fields"]["grids"][0]
    assert grid["fidelity"] is True
    assert grid["fidelity_tolerance"] > 0.0025 * bounding_box_diagonal(a.V)  # looser than the default
    assert grid["plain_deviation"] > grid["fidelity_tolerance"]  # the plain remeshing lost more
    assert _hausdorff(a, out) <= 0.005
    m = out.report["mesh"]
    assert m["junction_min_angle_p05"] >= 20.0
    assert m["junction_boundary_edges"] == 0 and m["new_non_manifold_edges"] == 0
    refined = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)], params=REMESHED)
    grid = refined.report["fields"]["grids"][0]
    assert grid["fidelity"] is True and "fidelity_retries" not in grid
    assert _hausdorff(a, refined) <= 0.005 and refined.report["mesh"]["junction_min_angle_p05"] >= 20.0


def test_the_looser_tolerance_never_costs_the_junction_its_triangles():
    """The Horse + Knight centaur: its plain junction strays more than the fidelity tolerance
    from the isosurface, so the shape-keeping retry is considered; a retry is taken only when
    its junction keeps p05 >= 20 degrees and loses at most ``relax_max_angle_loss``, even
    when any loss is allowed."""
    from conftest import ROOT

    from rigmix.config import load_config
    from rigmix.fusion import FusionParams
    from rigmix.fusion.inputs import fusion_inputs_from_plan
    from rigmix.pipeline import compose

    comp = compose(load_config(ROOT / "tests" / "configs" / "centaur.toml"), until="mapping")
    inputs, actions, _ = fusion_inputs_from_plan(comp.plan)
    params = FusionParams()
    for p in (params, FusionParams(relax_max_angle_loss=90.0)):
        out = fuse_surfaces(inputs, actions, params=p)
        grid = out.report["fields"]["grids"][0]
        p05 = out.report["mesh"]["junction_min_angle_p05"]
        assert p05 >= 20.0
        assert grid["plain_deviation"] > 4 * 0.0025 * bounding_box_diagonal(out.V)  # the retry was considered
        assert grid["fidelity_retries"]
        if grid["fidelity"]:  # the retry taken: within the acceptance level and the allowed loss
            taken = [r for r in grid["fidelity_retries"] if r["tolerance"] == grid["fidelity_tolerance"]]
            assert taken and taken[0]["junction_min_angle_p05"] >= 20.0
        else:
            assert grid["fidelity_tolerance"] == 0.0


def test_knight_leg_junction_is_remeshed_and_manifold():
    """Marching cubes emitted a triangle and its reverse on the Knight's hip (grid points on a
    planar face): four faces on one edge, the junction left unremeshed with 2-degree slivers."""
    from rigmix.io import load_character

    c = load_character(asset("Knight"))
    sub = c.skeleton.subtree(c.skeleton.index("UpperLeg.L"))
    out = fuse_surfaces([fusion_input(c, ~sub), fusion_input(c, sub)], [FusionAction("replace", 0, 1)], params=REMESHED)
    m = out.report["mesh"]
    assert all(g["remeshed"] for g in out.report["fields"]["grids"])
    assert m["new_non_manifold_edges"] == 0 and m["junction_boundary_edges"] == 0
    assert m["junction_min_angle_p05"] >= 20.0
