"""Seams that cannot close are opened up before the junction is made (``unpinch_preserved``).

The Witch's welded mesh flips orientation along a line that ends on a T-junction crack at her
collar: one pass of the collar's boundary through a vertex there has two outgoing half-edges.
Taken for a pinch, the faces around it (presence 1) left the preserved part and a junction grew
at the collar in every composition of hers, its seam ending on the crack as open chains.

The Frog's legs stand on her body along non-manifold edges: where two preserved faces close
such an edge and a junction face hangs from it, no seam runs along it and the seam stopped at
both its ends. Such edges are opened up only while a seam ends: where every seam closes (her
mirrored right hind leg), opening them left small seam loops that no isosurface hole matched.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import corpus

from rigmix.fusion.seams import closed_past_junction, pinched_faces

#: the corpus matrix's case, and the limb replaced instead of the matrix's (None: the same); the
#: Witch's clavicle joins her arm so that the junction runs along the collar's crack
CASES = {"mirror__Witch__Shoulder.L": ("mirror__Witch__UpperArm.L", {"UpperArm.": "Shoulder."}),
         "mirror__Witch__UpperArm.L": ("mirror__Witch__UpperArm.L", None),
         "mirror__Frog__FrontUpLeg.L": ("mirror__Frog__FrontUpLeg.L", None)}


def test_a_flipped_face_is_no_pinch():
    # a fan of three triangles around vertex 0, the middle one wound the other way
    F = np.array([[0, 1, 2], [0, 3, 2], [0, 3, 4]])
    assert not pinched_faces(F).any()
    assert not pinched_faces(F[:, ::-1]).any()


def test_two_fans_touching_at_a_vertex_are_pinched():
    F = np.array([[0, 1, 2], [0, 3, 4], [5, 6, 7]])  # two triangles share vertex 0 only
    assert pinched_faces(F).tolist() == [True, True, False]
    F[1] = F[1, ::-1]  # whatever their orientation
    assert pinched_faces(F).tolist() == [True, True, False]


def test_a_seam_ending_at_a_closed_edge_opens_it():
    # edge (0, 1) has three faces: two preserved, and a replaced one (2) that goes on to
    # preserved face 3 across edge (1, 4): that seam ends at vertex 1
    F = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [1, 5, 4]])
    preserved = np.array([True, True, False, True])
    replaced = ~preserved
    assert closed_past_junction(F, preserved, replaced).tolist() == [True, True, False, False]
    # one preserved face on it: an ordinary seam edge
    assert not closed_past_junction(F, preserved & [True, False, False, True], replaced).any()
    # nothing replaced hangs from it (a dropped part): no seam needed
    assert not closed_past_junction(F, preserved, np.zeros(4, bool)).any()


def test_closed_edges_stay_where_every_seam_closes():
    F = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [2, 1, 5]])  # the replaced face 2 meets no seam
    preserved = np.array([True, True, False, True])
    assert not closed_past_junction(F, preserved, ~preserved).any()


@pytest.fixture(scope="module", params=sorted(CASES))
def mirrored_limb(request, tmp_path_factory):
    """The fused surface of one of :data:`CASES` (the corpus matrix's config), composed up to
    its fusion."""
    from benchmarks.corpus_matrix import load_subjects, mirror_cases, write_configs
    from rigmix.pipeline import compose

    name = request.param.split("__")[1]
    corpus(name)  # skips, or fails under CI=true, when the character is missing
    case_name, rename = CASES[request.param]
    case = next(c for c in mirror_cases(load_subjects([name])) if c.name == case_name)
    config = write_configs([case], tmp_path_factory.mktemp("pinch"))[case_name]
    for old, new in (rename or {}).items():
        config.write_text(config.read_text().replace(f'joint = "{old}', f'joint = "{new}'))
    return compose(config, until="fusion").surface


def test_a_mirrored_limb_leaves_no_gap(mirrored_limb):
    m = mirrored_limb.report["mesh"]
    for key in ("junction_boundary_edges", "open_seam_edges", "new_non_manifold_edges", "unmatched_loops"):
        assert m[key] == 0, key
    # whatever crosses was crossing in the input already (her overlapping layers)
    assert m["junction_self_intersections"] == m["junction_crossings_inherited"]
