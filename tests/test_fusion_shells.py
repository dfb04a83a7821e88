"""A junction goes around the closed parts an input keeps whole (``shell_clearance_voxels``).

The Triceratops' tail grafted onto CyberpunkCharacter: the figure's hip plates are closed
secondary components, kept whole and never blended, sunk into the body the isosurface follows.
Made as usual, the junction runs through them and the repair cannot undo it; made again around
them, it crosses nothing.

The Wasp's right hind leg replaced by its mirrored left: the leg is a closed part of its own,
plugged into the thorax, and the thorax's preserved surface runs on inside the new leg's root up
to the seam. The faces it covers join the junction (:func:`rigmix.fusion.seams.under_kept_shells`),
so that the junction starts outside the leg.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import asset, corpus, fused_twice

from rigmix.fusion.meshutil import edge_counts
from rigmix.fusion.presence import compute_presence, kept_shells

CASE = "tail__CyberpunkCharacter__Triceratops"
#: both tests in one ``--dist loadgroup`` group, so that one worker composes the case
pytestmark = pytest.mark.xdist_group("fusion_shells")


@pytest.fixture(scope="session")
def tail_graft(tmp_path_factory):
    """``(inputs, fused, fused without the clearance)`` of :data:`CASE` (the corpus matrix's config)."""
    from benchmarks.corpus_matrix import load_subjects, tail_cases, write_configs

    names = CASE.split("__")[1:]
    for name in names:
        corpus(name)  # skips, or fails under CI=true, when a character is missing
    case = next(c for c in tail_cases(load_subjects(names)) if c.name == CASE)
    config = write_configs([case], tmp_path_factory.mktemp("shells"))[CASE]
    return fused_twice(config, shell_clearance_voxels=0)


def test_the_junction_goes_around_kept_parts(tail_graft):
    inputs, out, bare = tail_graft
    m, m0 = out.report["mesh"], bare.report["mesh"]
    assert m0["junction_self_intersections"] > 0  # through the plates, as made without the clearance
    assert m["junction_self_intersections"] == 0
    assert any(g.get("shell_clearance") for g in out.report["fields"]["grids"])
    assert not any(g.get("shell_clearance") for g in bare.report["fields"]["grids"])
    for key in ("junction_boundary_edges", "new_non_manifold_edges", "open_seam_edges"):
        assert m[key] == 0, key
    assert m["junction_min_angle_p05"] >= 20.0


def test_kept_shells_are_closed_secondary_parts(tail_graft):
    inputs, _, _ = tail_graft
    found = 0
    for x in inputs:
        P = compute_presence(x.V, x.F, x.W, x.used)
        S = kept_shells(P, np.ones(len(P.welded.F), bool))
        if not len(S):
            continue
        found += 1
        _, counts = edge_counts(S)
        assert np.all(counts == 2)  # closed: no boundary edge
        secondary = {tuple(sorted(f)) for f in P.welded.F[P.secondary].tolist()}
        assert {tuple(sorted(f)) for f in S.tolist()} <= secondary
    assert found  # the figure's plates


MIRROR_CASE = "mirror__Wasp__BottomLeg1.R"


@pytest.fixture(scope="session")
def mirrored_leg(tmp_path_factory):
    """``(inputs, fused, fused without the clearance)`` of :data:`MIRROR_CASE`."""
    from benchmarks.corpus_matrix import load_subjects, mirror_cases, write_configs

    asset("Wasp")
    case = next(c for c in mirror_cases(load_subjects(["Wasp"])) if c.name == MIRROR_CASE)
    config = write_configs([case], tmp_path_factory.mktemp("mirrored_leg"))[MIRROR_CASE]
    return fused_twice(config, shell_clearance_voxels=0)


def _made(mesh):
    return mesh["junction_self_intersections"] - mesh["junction_crossings_inherited"]


def test_a_plugged_in_part_covers_no_seam(mirrored_leg):
    inputs, out, bare = mirrored_leg
    import igl

    m = out.report["mesh"]
    leg = compute_presence(inputs[1].V, inputs[1].F, inputs[1].W, inputs[1].used)
    shell = kept_shells(leg, leg.preserved)

    def body_faces_inside_the_leg(surface):
        kept = ~surface.junction_faces & (surface.face_origin_input == 0)
        C = surface.V[surface.F[kept]].mean(axis=1)
        return int((igl.fast_winding_number(leg.welded.V, shell, C) > 0.5).sum())

    assert len(shell)
    # the thorax's kept surface runs on inside the leg's root; taken into the junction, it does
    # not (a face where the thorax passes through the leg's plug may keep its centre inside)
    inside, inside_bare = body_faces_inside_the_leg(out), body_faces_inside_the_leg(bare)
    assert inside_bare > 0 and inside <= inside_bare // 3
    assert _made(m) == 0
    for key in ("junction_boundary_edges", "new_non_manifold_edges", "open_seam_edges"):
        assert m[key] == 0, key
    assert m["junction_min_angle_p05"] >= 20.0


def test_faces_under_another_inputs_part_join_the_junction(mirrored_leg):
    import igl

    from rigmix.fusion.seams import under_kept_shells

    inputs, _, _ = mirrored_leg
    pres = [compute_presence(x.V, x.F, x.W, x.used) for x in inputs]
    preserved = [P.preserved.copy() for P in pres]
    junction = [~P.preserved & ~P.absent for P in pres]
    given = [p.copy() for p in preserved]
    out = under_kept_shells(pres, preserved, junction)
    assert all(np.array_equal(a, b) for a, b in zip(preserved, given))  # inputs untouched
    body, leg = pres
    taken = preserved[0] & ~out[0]
    assert 0 < taken.sum() < 0.05 * len(body.welded.F)
    assert np.array_equal(out[1], preserved[1])  # nothing covers the leg's own surface
    # every face taken reaches into the mirrored leg, which the output keeps whole
    shell = kept_shells(leg, preserved[1])
    w = igl.fast_winding_number(leg.welded.V, shell, body.welded.V[body.welded.F[taken].ravel()])
    assert np.all((w.reshape(-1, 3) > 0.5).any(axis=1))
    # and joins the junction through faces taken: no new hole
    reach = np.zeros(len(body.welded.V), bool)
    reach[body.welded.F[junction[0]].ravel()] = True
    left = taken.copy()
    while True:
        step = left & reach[body.welded.F].any(axis=1)
        if not step.any():
            break
        reach[body.welded.F[step].ravel()] = True
        left &= ~step
    assert not left.any()


def test_a_pinched_seam_bridged_from_both_sides_leaves_no_non_manifold_edge(tmp_path):
    """The Wasp's left fore leg replaced by its mirrored partner: the seam touches itself at a
    vertex, and the bridge reached one isosurface vertex from both sides of the pinch (four faces
    on one edge). Flipped apart, the output has no edge the inputs did not share."""
    from benchmarks.corpus_matrix import load_subjects, mirror_cases, write_configs
    from rigmix.pipeline import compose

    asset("Wasp")
    name = "mirror__Wasp__TopLeg1.L"
    case = next(c for c in mirror_cases(load_subjects(["Wasp"])) if c.name == name)
    m = compose(write_configs([case], tmp_path)[name], until="fusion").report["mesh"]
    assert m["junction_faces"] > 0
    for key in ("new_non_manifold_edges", "junction_boundary_edges", "open_seam_edges"):
        assert m[key] == 0, key
