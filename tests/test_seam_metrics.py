"""Issue 25's rest-pose surface figures (rigmix.quality) and their gates (rigmix.gates): how much of
each grafted part shows (``mesh.grafted_visible``, gate ``grafted_visible``) and how creased the
junction is against the inputs near the same joints (``mesh.junction_dihedral_p95`` /
``source_dihedral_p95``, gate ``junction_dihedral_ratio``).

The compositions stop after the fusion stage, which computes both figures."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import ROOT, asset, corpus, corpus_case

from dfd.mesh import face_areas, face_normals, vertex_normals
from rigmix import examples
from rigmix.fusion.meshutil import dihedral_angles
from rigmix.gates import MAX_DIHEDRAL_RATIO, MIN_GRAFTED_VISIBLE, failure_text, mesh_gates
from rigmix.geometry import bounding_box_diagonal
from rigmix.pipeline import compose
from rigmix.quality import face_owners, outside_area_share

CONFIGS = ROOT / "tests" / "configs"


def by_name(gates) -> dict:
    return {g.name: g for g in gates}


def config_copy(tmp_path, name: str, replace: tuple = (), extra: str = ""):
    """A copy of ``tests/configs/<name>.toml`` with ``replace`` (old, new) applied and ``extra`` appended."""
    text = (CONFIGS / f"{name}.toml").read_text()
    for old, new in replace:
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / f"{name}.toml"
    path.write_text(text + extra)
    return path


@pytest.fixture(scope="module")
def humanoid():
    """The built-in humanoid's surface: one closed, outward-oriented mesh, ``(V, F)``."""
    (mesh,) = examples.humanoid().meshes
    return np.asarray(mesh.positions, np.float64), np.asarray(mesh.faces, np.int64)


# --------------------------------------------------------------------------------------------
# the functions


def test_outside_area_share_tells_inside_from_outside(humanoid):
    V, F = humanoid
    offset = 0.003 * bounding_box_diagonal(V) * vertex_normals(V, F)
    assert outside_area_share(V + offset, F, [(V, F)]) > 0.99  # a skin just outside the body
    assert outside_area_share(V - offset, F, [(V, F)]) < 0.01  # and just inside it
    far = V + [2 * bounding_box_diagonal(V), 0, 0]
    assert outside_area_share(far, F, [(V, F)]) == 1.0
    assert outside_area_share(V - offset, F, []) == 1.0  # nothing to hide behind
    assert outside_area_share(V, F[:0], [(V, F)]) is None  # no area to measure
    # the inner skin of one half of the body (x < 0), the other half elsewhere: about half hidden
    left = (V - offset)[F].mean(axis=1)[:, 0] < 0
    inner = outside_area_share(np.concatenate([V - offset, far]), np.concatenate([F[left], F[~left] + len(V)]),
                               [(V, F)])
    assert 0.3 < inner < 0.7


def test_dihedral_angles_of_a_flat_shaded_box():
    """A box split at every face, as flat-shaded glTF meshes are: welded by position, its 12 edges
    are 90-degree creases and its 6 face diagonals flat."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]  # outward
    F = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    Vs, Fs = corners[F].reshape(-1, 3), np.arange(3 * len(F)).reshape(-1, 3)  # every face its own corners
    a = np.sort(dihedral_angles(Vs * 0.37, Fs))
    np.testing.assert_allclose(a, [0.0] * 6 + [90.0] * 12, atol=1e-9)
    # two sides of the box: their two diagonals and the one crease between them
    np.testing.assert_allclose(np.sort(dihedral_angles(Vs, Fs, [0, 1, 4, 5])), [0, 0, 90], atol=1e-9)


def test_dihedral_angles_of_a_real_mesh_are_rigid_invariant_and_see_a_fold(humanoid):
    V, F = humanoid
    a = dihedral_angles(V, F)
    assert len(a) == 3 * len(F) // 2  # closed: every edge between two faces
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    np.testing.assert_allclose(dihedral_angles(2.5 * V @ R.T + [1, -2, 3], F), a, atol=1e-6)
    # one face turned over: its three edges read 180 degrees less their angle, a fold onto itself
    flipped = F.copy()
    flipped[10] = flipped[10, ::-1]
    changed = np.abs(dihedral_angles(V, flipped) - a) > 1e-9
    assert changed.sum() == 3
    np.testing.assert_allclose(dihedral_angles(V, flipped)[changed], 180.0 - a[changed], atol=1e-6)


# --------------------------------------------------------------------------------------------
# real configs


def test_tail_graft_figures_are_measured_and_pass():
    asset("CesiumMan")
    asset("Velociraptor")
    comp = compose(CONFIGS / "tail_graft.toml", until="fusion")
    m = comp.report["mesh"]
    assert set(m["grafted_visible"]) == {"raptor"}  # the body is not a grafted part
    assert MIN_GRAFTED_VISIBLE <= m["grafted_visible"]["raptor"] <= 1.0
    assert 0 < m["grafted_visible_source"]["raptor"] <= 1.0
    assert m["grafted_visible_min"] == m["grafted_visible_relative"]["raptor"] >= m["grafted_visible"]["raptor"]
    assert 0 < m["junction_dihedral_p95"] < 180 and 0 < m["source_dihedral_p95"] < 180
    assert m["junction_dihedral_ratio"] == pytest.approx(m["junction_dihedral_p95"] / m["source_dihedral_p95"])
    gates = by_name(mesh_gates(m))
    assert gates["grafted_visible"].passed and "raptor" in gates["grafted_visible"].note
    assert gates["junction_dihedral_ratio"].passed and gates["junction_dihedral_ratio"].bound == MAX_DIHEDRAL_RATIO
    # every face belongs to an input: the raptor keeps its tail, generated junction faces included
    owner = face_owners(comp.surface)
    assert owner.min() >= 0 and np.count_nonzero(owner == comp.fusion_ids.index("raptor")) > np.count_nonzero(
        comp.surface.face_origin_input == comp.fusion_ids.index("raptor"))


#: Corpus matrix cases whose shape-keeping junction pinned the vertices its remeshing chorded off:
#: the remesher left each of them three faces standing over coarse triangles (dihedral p95 149
#: degrees on RiggedFigure's arm, 90 on the input there). The Rat's foreleg creases at the
#: corners of its low-poly paw even refined, and takes the plain junction.
CREASED = ("mirror__RiggedFigure__arm_joint_L_1", "mirror__Trex__BackUpLeg.L", "tail__RiggedFigure__Wolf",
           "mirror__Rat__FrontUpLeg.R")


@pytest.mark.parametrize("name", CREASED)
def test_a_shape_keeping_junction_creases_no_more_than_its_inputs(name, tmp_path):
    comp = compose(corpus_case(name, tmp_path), until="fusion")
    m = comp.report["mesh"]
    gate = by_name(mesh_gates(m))["junction_dihedral_ratio"]
    assert gate.passed is True, (m["junction_dihedral_p95"], m["source_dihedral_p95"])


#: Corpus matrix cases whose grafted part joins the body through a junction that narrows from
#: the body's opening to the part (a funnel): the Snake's head, rebuilt whole, on RiggedFigure's
#: neck, and the Wasp's mirrored middle leg. Winding numbers of the body's junction faces, open
#: where they meet the part, read 0.79 and 0.32 of the part's area as inside.
FUNNELS = ("head_swap__RiggedFigure__Snake", "mirror__Wasp__MidLeg1.L")


@pytest.mark.parametrize("name", FUNNELS)
def test_a_part_beside_the_bodys_junction_shows(name, tmp_path):
    import igl

    comp = compose(corpus_case(name, tmp_path), until="fusion")
    m = comp.report["mesh"]
    s = comp.surface
    V, F = np.asarray(s.V, np.float64), np.asarray(s.F, np.int64)
    (graft,) = m["grafted_visible"]
    mine = F[face_owners(s) == comp.fusion_ids.index(graft)]
    # what a viewer sees, measured apart from the figure: just off each face, outwards, is
    # outside the whole output (its winding number with respect to every output face)
    off = V[mine].mean(axis=1) + 1e-3 * bounding_box_diagonal(V) * face_normals(V, mine)
    w = igl.fast_winding_number(V, F, off)
    area = face_areas(V, mine)
    assert area[w < 0.5].sum() / area.sum() > MIN_GRAFTED_VISIBLE
    assert by_name(mesh_gates(m))["grafted_visible"].passed is True, m["grafted_visible_relative"]


def test_a_graft_buried_in_the_body_fails_the_visibility_gate(tmp_path):
    """The raptor's tail scaled to 1/30 of its matched size sits inside CesiumMan's hips: its
    faces are in the output, hidden."""
    asset("CesiumMan")
    asset("Velociraptor")
    cfg = config_copy(tmp_path, "tail_graft", [('scale = "auto"', "scale = 0.004  #")])
    comp = compose(cfg, until="fusion")
    m = comp.report["mesh"]
    assert np.any(comp.surface.face_origin_input == comp.fusion_ids.index("raptor"))  # in the output
    assert m["grafted_visible_relative"]["raptor"] < MIN_GRAFTED_VISIBLE
    assert m["grafted_visible_source"]["raptor"] > MIN_GRAFTED_VISIBLE  # in the raptor, its tail shows
    gate = by_name(mesh_gates(m))["grafted_visible"]
    assert gate.passed is False and failure_text([gate.as_dict()]).startswith("grafted_visible = ")


def test_a_copied_junction_and_a_removal_leave_the_gates_not_applicable(tmp_path):
    asset("CesiumMan")
    # a limb replaced by itself: the donor's arm is outside the body; its junction is copied
    m = compose(CONFIGS / "self_composition.toml", until="fusion").report["mesh"]
    assert m["grafted_visible_relative"] == {"donor": pytest.approx(1.0)}
    assert m["junction_dihedral_p95"] is None and m["junction_dihedral_ratio"] is None
    gate = by_name(mesh_gates(m))["junction_dihedral_ratio"]
    assert gate.value is None and gate.passed is True and "copied" in gate.note
    # a removal: one character, no graft; its capped cut is a junction with no fused joint around it
    cfg = tmp_path / "remove.toml"
    cfg.write_text('name = "one_armed"\n[characters.man]\npath = "${RIGMIX_ASSETS}/CesiumMan/CesiumMan.glb"\n'
                   '[[actions]]\nop = "remove"\ntarget = "man"\ntarget_joint = "Skeleton_arm_joint_L__4_"\n')
    m = compose(cfg, until="fusion").report["mesh"]
    assert m["grafted_visible_relative"] == {} and m["grafted_visible_min"] is None
    assert m["junction_dihedral_p95"] is not None and m["source_dihedral_p95"] is None
    gates = by_name(mesh_gates(m))
    assert gates["grafted_visible"].passed is True and gates["grafted_visible"].note == "no grafted part"
    assert gates["junction_dihedral_ratio"].passed is True and "no joint fused" in gates["junction_dihedral_ratio"].note


def test_parts_a_character_hides_in_itself_do_not_fail_an_identity_composition(tmp_path):
    """The Crab's legs and claws reach into its shell: replaced by themselves, they are as hidden
    as in the Crab itself, and the composition passes."""
    corpus("Crab")
    cfg = tmp_path / "crab.toml"
    cfg.write_text('name = "crab"\n[characters.body]\npath = "${RIGMIX_CORPUS}/Crab/Crab.glb"\n'
                   '[characters.donor]\npath = "${RIGMIX_CORPUS}/Crab/Crab.glb"\n[[actions]]\nop = "replace"\n'
                   'source = "donor"\nsource_joint = "Body"\ntarget = "body"\ntarget_joint = "Body"\n')
    m = compose(cfg, until="fusion").report["mesh"]
    assert m["grafted_visible"]["donor"] < 0.99  # part of it is inside the Crab's other faces
    assert m["grafted_visible_source"]["donor"] == pytest.approx(m["grafted_visible"]["donor"])
    assert m["grafted_visible_relative"]["donor"] == pytest.approx(1.0)
    assert by_name(mesh_gates(m))["grafted_visible"].passed is True


def test_the_gates_fail_past_their_bounds():
    mesh = {"grafted_visible": {"rider": 0.95, "fox": 0.3}, "grafted_visible_source": {"rider": 1.0, "fox": 0.75},
            "grafted_visible_relative": {"rider": 0.95, "fox": 0.4}, "grafted_visible_min": 0.4,
            "junction_dihedral_p95": 80.0, "source_dihedral_p95": 40.0, "junction_dihedral_ratio": 2.0}
    gates = by_name(mesh_gates(mesh))
    assert gates["grafted_visible"].passed is False and gates["grafted_visible"].value == 0.4
    assert "fox (0.3 of its output area shows, 0.75 in its own character)" in gates["grafted_visible"].note
    assert gates["junction_dihedral_ratio"].passed is False and gates["junction_dihedral_ratio"].value == 2.0
    gates = by_name(mesh_gates({}))  # a report without the figures: not evaluated, not passed
    assert gates["grafted_visible"].passed is None and gates["junction_dihedral_ratio"].passed is None
