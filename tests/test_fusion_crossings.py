"""Crossing faces at the junction are repaired (:mod:`rigmix.fusion.crossings`), not tolerated.

Synthetic cases with known crossings (a junction vertex pulled through the surface, a kept
seam vertex raised through the junction, an overlapping part of an input) and a real
composition (CesiumMan's arm and leg replaced by RiggedFigure's), with and without the repair.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import ROOT, asset, corpus, fused_twice
from fusion_shapes import sphere

from rigmix.fusion.crossings import (
    fan_fill,
    flip_apart,
    flip_for_angles,
    knot_regions,
    repair_crossings,
    repair_junction,
)
from rigmix.fusion.meshutil import edge_counts, intersecting_face_pairs, triangle_min_angles, vertex_adjacency


@pytest.fixture(scope="module")
def capped_sphere():
    """A sphere whose cap (faces above z = 0.5) is the junction: ``(V, F, cap, movable)``."""
    V, F = sphere(3)
    cap = (V[F][:, :, 2] > 0.5).all(axis=1)
    on_kept = np.zeros(len(V), bool)
    on_kept[F[~cap].ravel()] = True
    return V, F, cap, ~on_kept


def _crossings(V, F, junction):
    return len(intersecting_face_pairs(V, F, np.flatnonzero(junction)))


def test_a_fold_through_the_surface_is_smoothed_open(capped_sphere):
    V, F, cap, movable = capped_sphere
    V = V.copy()
    V[np.argmax(V[:, 2])] = [0.05, 0.02, -1.2]  # the cap's top pulled through the bottom
    assert _crossings(V, F, cap) > 0
    rep = repair_crossings(V, F, movable, cap, target=0.15)
    assert rep.found == _crossings(V, F, cap) and rep.left == 0
    assert _crossings(rep.V, F, cap) == 0
    assert np.array_equal(rep.V[~movable], V[~movable])  # kept vertices bit-identical
    assert not rep.released.any()
    again = repair_crossings(V, F, movable, cap, target=0.15)
    assert np.array_equal(again.V, rep.V)  # deterministic


def _crumpled(capped_sphere, seed, rings=1):
    """The cap's top and ``rings`` rings around it shrunk to a speck and scattered: tiny triangles
    folded through each other (a knot), one ring apart."""
    V, F, cap, movable = capped_sphere
    A = vertex_adjacency(F, len(V)).tocsr()
    top = int(np.argmax(V[:, 2]))
    inner = np.array([top])
    for _ in range(rings):
        inner = np.union1d(inner, np.concatenate([A[v].indices for v in inner]))
    U = V.copy()
    scatter = np.random.default_rng(seed).normal(scale=0.01, size=(len(inner), 3))
    U[inner] = V[top] + 0.03 * (V[inner] - V[top]) + scatter
    return U, inner


def _kept_and_junction(U, F, cap):
    """``(KV, KF, JV, JF)``: the kept faces (outside ``cap``) and the junction (``cap``), each over
    its own vertices, as :func:`repair_junction` takes them."""
    out = []
    for faces in (~cap, cap):
        used = np.unique(F[faces])
        new = np.full(len(U), -1)
        new[used] = np.arange(len(used))
        out += [U[used], new[F[faces]]]
    return tuple(out)


@pytest.mark.parametrize("seed", [1, 3, 4])
def test_a_knot_is_filled_again_as_a_fan_without_crossings(capped_sphere, seed):
    V, F, cap, movable = capped_sphere
    U, inner = _crumpled(capped_sphere, seed)
    pairs = intersecting_face_pairs(U, F, np.flatnonzero(cap))
    assert len(pairs) > 0
    _, count = edge_counts(F)
    regions = knot_regions(F, len(U), ~movable, pairs)
    assert len(regions) == 1
    R, loop = regions[0]
    assert cap[R].all() and set(inner) <= set(F[R].ravel())  # the knot, inside the junction
    V2, F2, origin = fan_fill(U, F, regions)
    assert len(V2) == len(U) + 1 and len(F2) == len(F) - len(R) + len(loop)
    assert np.array_equal(F2[:len(F) - len(R)], F[np.setdiff1d(np.arange(len(F)), R)])  # the rest, in order
    assert np.all(origin[len(F) - len(R):] == R[0])
    assert len(intersecting_face_pairs(V2, F2)) == 0
    _, count2 = edge_counts(F2)
    assert count2.max() == 2 and (count2 == 1).sum() == (count == 1).sum() == 0  # still closed, manifold
    E = np.concatenate([F2[:, [0, 1]], F2[:, [1, 2]], F2[:, [2, 0]]])
    assert len(np.unique(E, axis=0)) == len(E)  # every edge once each way: the orientation kept


def test_a_knot_with_a_fixed_inner_vertex_is_not_taken(capped_sphere):
    V, F, cap, movable = capped_sphere
    U, inner = _crumpled(capped_sphere, 3)
    pairs = intersecting_face_pairs(U, F, np.flatnonzero(cap))
    fixed = np.zeros(len(U), bool)
    fixed[inner] = True
    assert knot_regions(F, len(U), fixed, pairs) == []


def test_repair_junction_unties_a_knot_no_vertex_move_undoes(capped_sphere):
    V, F, cap, movable = capped_sphere
    U, _ = _crumpled(capped_sphere, 3, rings=2)
    found = len(intersecting_face_pairs(U, F, np.flatnonzero(cap)))
    assert repair_crossings(U, F, movable, cap, target=0.15).left == found > 0  # moves alone undo nothing
    KV, KF, JV, JF = _kept_and_junction(U, F, cap)
    rep = repair_junction(KV, KF, JV, JF, counted=np.zeros(len(KF), bool))
    assert rep.left == 0 and rep.found >= found
    assert rep.moved and len(rep.JF) < len(JF) and len(rep.made) == len(JF) and not rep.made.any()
    from rigmix.geometry import weld

    Vw, _, Fw = weld(np.concatenate([KV, rep.JV]), np.concatenate([KF, rep.JF + len(KV)]))
    assert len(intersecting_face_pairs(Vw, Fw)) == 0
    _, count = edge_counts(Fw)
    assert count.max() == 2 and count.min() == 2  # the sphere is closed again, every edge twice


def test_repair_junction_refills_no_knot_where_moves_suffice(capped_sphere):
    """A crumple the vertex moves undo keeps its faces: the knots are a fallback."""
    V, F, cap, movable = capped_sphere
    U, _ = _crumpled(capped_sphere, 3)
    assert repair_crossings(U, F, movable, cap, target=0.15).left == 0
    KV, KF, JV, JF = _kept_and_junction(U, F, cap)
    rep = repair_junction(KV, KF, JV, JF, counted=np.zeros(len(KF), bool))
    assert rep.left == 0 and len(rep.JF) == len(JF)


def test_a_kept_part_in_the_way_joins_the_junction(capped_sphere):
    """A seam vertex raised through the cap: no junction vertex can move the kept faces out of
    the way; released into the junction, they can."""
    V, F, cap, movable = capped_sphere
    seam = np.flatnonzero(~movable & np.isin(np.arange(len(V)), F[cap].ravel()))
    v = seam[np.argmax(V[seam, 0])]
    V = V.copy()
    V[v] = 0.3 * V[v] + [0.0, 0.0, 0.9]
    assert _crossings(V, F, cap) > 0
    assert repair_crossings(V, F, movable, cap, target=0.15).left > 0  # nothing to move without release
    rep = repair_crossings(V, F, movable, cap, target=0.15, releasable=~cap)
    assert rep.left == 0 and rep.released.any()
    junction = cap | rep.released
    assert _crossings(rep.V, F, junction) == 0
    on_kept = np.zeros(len(V), bool)
    on_kept[F[~junction].ravel()] = True
    assert np.array_equal(rep.V[on_kept], V[on_kept])  # what stays kept is untouched


def test_an_overlapping_part_of_an_input_is_counted_not_worked_on(capped_sphere):
    """A kept plate through the cap that crosses its own input too (a pad through the arm it
    covered): the junction is left as it is and the pairs are reported as layered."""
    V, F, cap, movable = capped_sphere
    plate = np.array([[-0.3, -0.3, 0.95], [0.3, -0.3, 0.95], [0.3, 0.3, 0.95], [-0.3, 0.3, 0.95]])
    V2 = np.concatenate([V, plate])
    n = len(V)
    F2 = np.concatenate([F, [[n, n + 1, n + 2], [n, n + 2, n + 3]]])
    cap2 = np.concatenate([cap, [False, False]])
    movable2 = np.concatenate([movable, [False] * 4])
    found = _crossings(V2, F2, cap2)
    assert found > 0
    rep = repair_crossings(V2, F2, movable2, cap2, target=0.15, releasable=~cap2,
                           layered=lambda faces: faces >= len(F))
    assert rep.found == rep.left == rep.layered == found
    assert np.array_equal(rep.V, V2) and not rep.released.any()


def _grid(g, z):
    """A flat square grid over ``g x g`` (``(k,)`` coordinates) at height ``z``, each square two
    triangles: ``(V (k^2, 3), F (2 (k-1)^2, 3))``."""
    k = len(g)
    X, Y = np.meshgrid(g, g, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.full(X.size, float(z))], axis=1)
    i = (np.arange(k - 1)[:, None] * k + np.arange(k - 1)[None, :]).ravel()
    a, b, c, d = i, i + k, i + k + 1, i + 1
    return V, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _sheet_and_piece(half, centre):
    """A flat junction sheet (5 x 5 unit squares at z = 0, its border fixed) and a kept closed
    box ``(2 half)`` wide around ``centre``, apart from it: ``(V, F, junction, movable)``."""
    Vs, Fs = _grid(np.arange(6.0), 0.0)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    Vb = np.asarray(centre) + half * corners
    Fb = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                   [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    V = np.concatenate([Vs, Vb])
    F = np.concatenate([Fs, Fb + 36])
    junction = np.arange(len(F)) < len(Fs)
    border = (Vs[:, 0] % 5 == 0) | (Vs[:, 1] % 5 == 0)
    movable = np.concatenate([~border, np.zeros(8, bool)])
    return V, F, junction, movable


def test_kept_parts_are_the_pieces_apart_from_the_junction():
    from rigmix.fusion.crossings import kept_parts

    V, F, junction, movable = _sheet_and_piece(0.3, (2.5, 2.5, 0.2))
    part, closed = kept_parts(F, len(V), ~movable)
    assert np.all(part[junction] == -1)  # the sheet has movable vertices
    assert len(np.unique(part[~junction])) == 1 and closed[part[~junction][0]]
    open_box = F[:-1]  # a face less: a box with a hole is no closed piece
    part, closed = kept_parts(open_box, len(V), ~movable)
    assert not closed[part[~junction[:-1]][0]]


@pytest.mark.parametrize("centre", [(2.5, 2.5, 0.2), (2.0, 2.0, 0.2)], ids=["corners_poke", "vertex_inside"])
def test_a_junction_goes_off_a_kept_piece_it_cuts(centre):
    """A rigid piece, mostly above the junction, cuts through it: its corners poke through a
    junction face with no junction vertex inside it (the face is moved along its normal), or a
    junction vertex lies inside it (taken out to its surface). The junction ends below it."""
    V, F, junction, movable = _sheet_and_piece(0.3, centre)
    assert _crossings(V, F, junction) > 0
    rep = repair_crossings(V, F, movable, junction, target=1.0)
    assert rep.found > 0 and rep.left == 0
    assert _crossings(rep.V, F, junction) == 0
    moved = np.linalg.norm(rep.V - V, axis=1) > 0
    assert not moved[~movable].any()
    assert np.all(rep.V[moved, 2] < 0)  # off the side the piece lies on
    assert np.all(rep.V[moved, 2] > -0.6)  # by about the piece's depth below the sheet


def test_open_borders_never_move(capped_sphere):
    """A vertex on an open border keeps its position even when it is free to move: moving it
    would open a gap the report counts as a new boundary edge."""
    V, F, cap, movable = capped_sphere
    top = int(np.argmax(V[:, 2]))
    ring = np.flatnonzero((F == top).any(axis=1))
    F_open = np.delete(F, ring[:1], axis=0)  # a hole at the top: its corners are on the border
    cap_open = np.delete(cap, ring[:1])
    V = V.copy()
    V[top] = [0.05, 0.02, -1.2]
    rep = repair_crossings(V, F_open, movable, cap_open, target=0.15)
    border = np.unique(F[ring[0]])
    assert np.array_equal(rep.V[border], V[border])


def test_no_rounds_repair_nothing(capped_sphere):
    V, F, cap, movable = capped_sphere
    V = V.copy()
    V[np.argmax(V[:, 2])] = [0.05, 0.02, -1.2]
    rep = repair_crossings(V, F, movable, cap, target=0.15, rounds=0)
    assert rep.found > 0 and rep.left == rep.found and np.array_equal(rep.V, V)


@pytest.fixture(scope="module")
def limb_swap():
    """The fusion of tests/configs/limb_swap.toml, with and without the repair."""
    for name in ("CesiumMan", "RiggedFigure"):
        asset(name)
    return fused_twice(ROOT / "tests" / "configs" / "limb_swap.toml", crossing_rounds=0)


def test_a_real_junction_crosses_nothing_after_the_repair(limb_swap):
    inputs, out, bare = limb_swap
    m, m0 = out.report["mesh"], bare.report["mesh"]
    assert m["junction_self_intersections"] == 0
    # the figures the repair reports are those of the surface it repaired
    assert m0["junction_self_intersections"] == m["junction_crossings_repaired"] + m["junction_self_intersections"]
    for key in ("boundary_edges", "junction_boundary_edges", "new_non_manifold_edges", "open_seam_edges"):
        assert m[key] <= m0[key], key
    if m0["junction_min_angle_p05"] is not None and m0["junction_min_angle_p05"] >= 20.0:
        assert m["junction_min_angle_p05"] >= 20.0
    # kept vertices are the inputs' own, bit for bit
    kept = out.origin_input >= 0
    for i, x in enumerate(inputs):
        mine = kept & (out.origin_input == i)
        assert np.array_equal(out.V[mine], np.asarray(x.V)[out.origin_vertex[mine]])


def test_crossings_with_overlapping_input_parts_are_inherited_not_new(tmp_path):
    """The Adventurer is modular: its head shell and backpack pass through its body. Swapping in
    CesiumMan's arm remeshes the shoulder they passed through, so they pass through the junction:
    those pairs are inherited (each kept face there belongs to a part that crosses another part
    of its own input), and the gate counts none of them; the report keeps the total."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from dfd.mesh import weld
    from rigmix.gates import crossing_gate
    from rigmix.pipeline import compose

    cfg = tmp_path / "arm.toml"
    cfg.write_text(f'[characters.body]\npath = "{corpus("Adventurer").as_posix()}"\n'
                   f'[characters.donor]\npath = "{asset("CesiumMan").as_posix()}"\nscale = "auto"\n'
                   '[[actions]]\nop = "replace"\nsource = "donor"\nsource_joint = "Skeleton_arm_joint_L__4_"\n'
                   'target = "body"\ntarget_joint = "Shoulder.L"\nmode = "blend"\n')
    comp = compose(cfg, until="fusion")
    out, mesh = comp.surface, comp.surface.report["mesh"]
    assert mesh["junction_self_intersections"] > 0  # the case this test is about
    assert mesh["junction_crossings_inherited"] == mesh["junction_self_intersections"]
    gate = crossing_gate(mesh)
    assert gate.value == 0 and gate.passed and "inherited" in gate.note

    Vw, _, Fw = weld(out.V, out.F)
    junction = out.junction_faces & ~out.copied_faces
    pairs = intersecting_face_pairs(Vw, Fw, np.flatnonzero(junction))
    kept = np.where(junction[pairs[:, 0]], pairs[:, 1], pairs[:, 0])
    assert not junction[kept].any() and (out.face_origin_input[kept] == 0).all()
    body = comp.fusion_inputs[0]
    V, _, F = weld(body.V, body.F)
    n = len(V)
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    _, part = connected_components(coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(n, n)), directed=False)
    own = intersecting_face_pairs(V, F)
    overlapping = set(part[F[own[part[F[own[:, 0], 0]] != part[F[own[:, 1], 0]]].ravel(), 0]].tolist())
    assert set(part[F[out.face_origin_face[kept], 0]].tolist()) <= overlapping


def _folded_quad():
    """A quad folded along its diagonal A-C into a valley (two junction faces, all four corners
    on its border, so none can move), and a small level kept triangle the valley cuts through
    and the ridge of the other diagonal B-D clears: ``(Q, valley, T)``."""
    Q = np.array([[0, 0, 0], [1, 0, 1], [1, 1, 0], [0, 1, 1]], float)
    valley = np.array([[0, 1, 2], [0, 2, 3]])
    T = np.array([[0.85, 0.15, 0.5], [0.15, 0.85, 0.5], [0.55, 0.55, 0.5]])
    return Q, valley, T


def test_a_fold_with_the_wrong_diagonal_is_flipped_apart():
    Q, valley, T = _folded_quad()
    V, F = np.concatenate([Q, T]), np.concatenate([valley, [[4, 5, 6]]])
    assert len(intersecting_face_pairs(V, F)) == 2  # both halves of the valley cut the triangle
    rep = repair_junction(T, np.array([[0, 1, 2]]), Q, valley, counted=np.zeros(1, bool))
    assert rep.found == 2 and rep.left == 0 and rep.moved and not rep.made.any()
    assert np.array_equal(rep.JV, Q)  # no vertex moved: the faces took the other diagonal
    assert {tuple(sorted(f)) for f in rep.JF} == {(0, 1, 3), (1, 2, 3)}
    uE, cnt = edge_counts(rep.JF)
    assert len(uE) == 5 and (cnt == 1).sum() == 4  # still one quad with its border
    out = np.concatenate([rep.JF, [[4, 5, 6]]])
    assert len(intersecting_face_pairs(V, out)) == 0


@pytest.mark.parametrize("case", ["kept face", "ignored", "edge exists"])
def test_a_flip_stands_only_between_two_junction_faces_and_for_counted_crossings(case):
    Q, valley, T = _folded_quad()
    V, F = np.concatenate([Q, T]), np.concatenate([valley, [[4, 5, 6]]])
    flippable, ignored = np.array([True, True, False]), None
    if case == "kept face":  # half of the quad is a kept face: its corners cannot change
        flippable[1] = False
    elif case == "ignored":  # the triangle crosses its own input: its pairs are not worked on
        ignored = np.array([False, False, True])
    else:  # B-D is an edge already (a face beside the quad): the flip would double it
        V = np.concatenate([V, [[2.0, 2.0, 1.0]]])
        F = np.concatenate([F, [[3, 1, 7]]])
        flippable, ignored = np.append(flippable, False), None
    made = np.ones(len(F), bool)
    F2, flipped, removed, made2 = flip_apart(V, F, flippable, made, ignored=ignored, reach=0.5, floor=0.0)
    assert np.array_equal(F2, F) and not flipped.any() and removed == 0
    assert made2[0] == (case != "ignored")  # the valley's first half still crosses what counts



def _sliver_quad(lift=0.0):
    """A long thin rhombus split along its long diagonal A-C (two slivers of about 11 degrees),
    the short diagonal B-D lifted by ``lift`` out of the plane: ``(Q, slivers)``."""
    Q = np.array([[0, 0, 0], [1, -0.1, lift], [2, 0, 0], [1, 0.1, lift]], float)
    return Q, np.array([[0, 1, 2], [0, 2, 3]])


def test_slivers_of_a_flat_quad_take_the_diagonal_with_larger_angles():
    Q, F = _sliver_quad()
    before = triangle_min_angles(Q, F).min()
    F2, flipped = flip_for_angles(Q, F, np.ones(2, bool), floor=20.0, reach=0.5)
    assert flipped.all() and {tuple(sorted(f)) for f in F2} == {(0, 1, 3), (1, 2, 3)}
    assert triangle_min_angles(Q, F2).min() > 2 * before
    # the same quad, oriented the same way (the normals of the new faces agree with the old)
    n = np.cross(Q[F[:, 1]] - Q[F[:, 0]], Q[F[:, 2]] - Q[F[:, 0]]).sum(axis=0)
    n2 = np.cross(Q[F2[:, 1]] - Q[F2[:, 0]], Q[F2[:, 2]] - Q[F2[:, 0]])
    assert (n2 @ n > 0).all()
    uE, cnt = edge_counts(F2)
    assert len(uE) == 5 and (cnt == 1).sum() == 4


@pytest.mark.parametrize("case", ["bent", "kept face", "crossing", "no sliver"])
def test_an_angle_flip_keeps_the_shape_the_kept_faces_and_the_crossings(case):
    # bent: the halves fold by 53 degrees along A-C; else by 11 (B, D lifted by 0.01)
    Q, F = _sliver_quad(lift={"bent": 0.05, "crossing": 0.01}.get(case, 0.0))
    V, flippable, floor = Q, np.ones(2, bool), 20.0
    if case == "kept face":
        flippable[1] = False
    elif case == "crossing":  # a kept fin standing on the valley A-C, through the ridge B-D would make
        V = np.concatenate([Q, [[0.9, 0, 0.005], [1.1, 0, 0.005], [1.0, 0, 0.2]]])
        F = np.concatenate([F, [[4, 5, 6]]])
        flippable = np.array([True, True, False])
        assert len(intersecting_face_pairs(V, F)) == 0
        ridge = np.concatenate([[[0, 1, 3], [1, 2, 3]], F[2:]])
        assert len(intersecting_face_pairs(V, ridge)) > 0
    elif case == "no sliver":
        floor = 5.0  # both faces are above it
    F2, flipped = flip_for_angles(V, F, flippable, floor=floor, reach=0.5)
    assert np.array_equal(F2, F) and not flipped.any()


def test_crossing_gate_counts_what_the_inputs_did_not_have():
    from rigmix.gates import crossing_gate

    assert crossing_gate({"junction_self_intersections": 82, "junction_crossings_inherited": 79}).value == 3
    assert not crossing_gate({"junction_self_intersections": 82, "junction_crossings_inherited": 79}).passed
    assert crossing_gate({"junction_self_intersections": 0}).passed
    assert crossing_gate({}).value is None


def _sphere_and_sheet(z, half=0.6):
    """A unit sphere whose cap above z = 0.5 is replaced, and a kept flat sheet (12 x 12 squares
    over [-half, half]^2) at height ``z``, apart from it: ``(V, F, kept, sheet faces)``."""
    V, F = sphere(3)
    Vs, Fs = _grid(np.linspace(-half, half, 13), z)
    Fs = Fs + len(V)
    kept = np.concatenate([~(V[F][:, :, 2] > 0.5).all(axis=1), np.ones(len(Fs), bool)])
    return np.concatenate([V, Vs]), np.concatenate([F, Fs]), kept, np.arange(len(F), len(F) + len(Fs))


def test_a_kept_sheet_through_the_replaced_surface_is_layered_where_it_lies_against_it():
    """A sheet through the replaced cap (a sleeve through the arm the junction replaces): its
    faces within reach of the cap, around the circle where it crosses, are its layering; its
    faces further from the cap, and the sphere's own faces, are not."""
    from rigmix.fusion.crossings import layer_faces

    V, F, kept, sheet = _sphere_and_sheet(0.9)
    reach = 0.05
    layered = layer_faces(V, F, kept, sheet, reach=reach)
    C = V[F[sheet]].mean(axis=1)
    r = np.linalg.norm(C[:, :2], axis=1)
    gap = np.abs(np.sqrt(r ** 2 + 0.81) - 1.0)  # centre's distance to the sphere
    crossing = np.isin(sheet, intersecting_face_pairs(V, F, sheet).ravel())
    assert crossing.any() and layered[crossing].all()
    assert layered.any() and not layered[gap > reach + 0.1].any()  # a face is about 0.14 wide
    assert layered[gap < 0.5 * reach].all()
    assert not layer_faces(V, F, kept, np.flatnonzero(kept[:len(F) - len(sheet)]), reach=reach).any()


def test_a_kept_sheet_through_the_kept_surface_beside_the_replaced_one_is_layered_within_reach():
    """A sheet through the sphere just below the replaced cap (a plate through the hip of a leg
    the junction replaces) is layered into the surface the junction continues, where it lies
    within reach of the cap; further from the cap than the reach, it is not."""
    from rigmix.fusion.crossings import layer_faces

    V, F, kept, sheet = _sphere_and_sheet(0.45, half=1.0)
    cap = V[F[~kept]]
    crossing = np.isin(sheet, intersecting_face_pairs(V, F, sheet).ravel())
    C = V[F[sheet[crossing]]].mean(axis=1)
    gap = np.linalg.norm(C[:, None] - cap.reshape(-1, 3)[None], axis=2).min(axis=1)
    assert crossing.any() and gap.max() < 0.3  # through the kept sphere, beside the cap
    assert layer_faces(V, F, kept, sheet, reach=0.3)[crossing].all()
    assert not layer_faces(V, F, kept, sheet, reach=0.02).any()


@pytest.mark.parametrize("z", [-0.9, 1.02], ids=["through_the_kept_surface_far", "near_but_apart"])
def test_a_kept_sheet_that_does_not_pass_through_the_surface_near_the_replaced_one_is_not_layered(z):
    """Through the kept part of the sphere far from the cap, or a hair above the cap without
    crossing it: a junction that crosses it there made the crossing."""
    from rigmix.fusion.crossings import layer_faces

    V, F, kept, sheet = _sphere_and_sheet(z)
    assert not layer_faces(V, F, kept, sheet, reach=0.05).any()


def test_boxes_meet_finds_what_comparing_every_pair_finds():
    """The chunked broad phase of the crossing repair's near faces (each chunk of boxes compared
    only with the queries that meet its bounding box) against every box compared with every
    query: the same boxes, for boxes of very different sizes and an empty side."""
    from rigmix.fusion.meshutil import boxes_meet

    rng = np.random.default_rng(3)
    for n, q, margin in ((4000, 1500, 0.05), (700, 9000, 0.0), (1, 3, 0.2), (5, 0, 0.1), (0, 5, 0.1)):
        lo = rng.random((n, 3)) * 10
        hi = lo + rng.random((n, 3)) * rng.choice([0.01, 0.5, 4.0], (n, 1))
        qlo = rng.random((q, 3)) * 10
        qhi = qlo + rng.random((q, 3)) * 0.3
        got = boxes_meet(lo, hi, qlo, qhi, margin)
        every = (lo[:, None] <= qhi[None] + margin) & (qlo[None] <= hi[:, None] + margin)  # every pair
        assert np.array_equal(got, every.all(axis=2).any(axis=1))
        assert n < 100 or 0 < got.sum() < n  # neither all nor none: the test can tell


def _triangle_soup(rng, n):
    """``n`` random triangles in a 10 m box, of very different sizes, many crossing."""
    centre = rng.random((n, 1, 3)) * 10
    size = rng.choice([0.05, 0.5, 3.0], (n, 1, 1))
    V = (centre + rng.normal(size=(n, 3, 3)) * size).reshape(-1, 3)
    return V, np.arange(3 * n).reshape(n, 3)


@pytest.mark.parametrize("seed", [0, 1])
def test_crossing_pairs_of_some_faces_are_those_of_all_faces_that_have_one(seed):
    """``intersecting_face_pairs`` with ``faces`` (the broad phase on the faces whose boxes meet
    their joint box) gives exactly the pairs of the whole search that hold one of them, in the
    same order, one of them first; for scattered and for clustered query faces."""
    rng = np.random.default_rng(seed)
    V, F = _triangle_soup(rng, 3000)
    every = intersecting_face_pairs(V, F)
    assert len(every) > 100
    lo = V[F].min(axis=1)
    most = np.argsort(-np.bincount(every.ravel(), minlength=len(F)), kind="stable")[:20]  # each alone
    for faces in (rng.choice(len(F), 40, replace=False), np.flatnonzero(np.all(lo < 2.5, axis=1)),
                  np.array([7]), np.zeros(0, np.int64), *most[:, None]):
        got = intersecting_face_pairs(V, F, faces)
        mask = np.isin(every, faces)
        want = every[mask.any(axis=1)]
        want = np.where(mask[mask.any(axis=1)][:, :1], want, want[:, ::-1])  # the query face first
        assert np.array_equal(np.sort(got, axis=1), np.sort(want, axis=1))
        assert np.isin(got[:, 0], faces).all()
    assert 0 < len(intersecting_face_pairs(V, F, np.flatnonzero(np.all(lo < 2.5, axis=1)))) < len(every)


def test_near_faces_of_several_queries_are_the_union_of_each_ones():
    """The crossing repair's near faces (cells of the query faces and their neighbours; only the
    boxes inside the queries' window split into cells) are, for queries far apart, the union of
    the near faces of each query alone: the window drops nothing any query reaches."""
    from rigmix.fusion.crossings import near_faces

    rng = np.random.default_rng(4)
    V, F = _triangle_soup(rng, 4000)
    for margin in (0.1, 0.6):
        query = np.zeros(len(F), bool)
        query[rng.choice(len(F), 12, replace=False)] = True
        got = near_faces(V, F, query, margin)
        union = np.zeros(len(F), bool)
        for q in np.flatnonzero(query):
            one = np.zeros(len(F), bool)
            one[q] = True
            union |= near_faces(V, F, one, margin)
        assert np.array_equal(got, union)
        assert query.sum() < got.sum() < len(F)
