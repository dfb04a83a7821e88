"""A junction goes around the closed parts an input keeps whole (``shell_clearance_voxels``).

The Triceratops' tail grafted onto CyberpunkCharacter: the figure's hip plates are closed
secondary components, kept whole and never blended, sunk into the body the isosurface follows.
Made as usual, the junction runs through them and the repair cannot undo it; made again around
them, it crosses nothing.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import corpus, fused_twice

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
