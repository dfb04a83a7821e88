"""Fusion of the example compositions (built-in characters): the operations issue's configs.

Acceptance of the fusion issue on every config: no gap at the seams, no new non-manifold
edge, junction min-angle 5th percentile >= 20 degrees, watertight (the inputs are closed).
"""

from pathlib import Path

import numpy as np
import pytest
from conftest import IN_COMPOSED_GROUP

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


@IN_COMPOSED_GROUP
@pytest.mark.parametrize("name", ["centaur", "self_arm", "beast_arms", "tailed_humanoid"])
def test_example_fuses_cleanly(name, composed):
    comp = composed(EXAMPLES / f"{name}.toml")
    surface = comp.surface
    m = comp.surface.report["mesh"]
    assert m["junction_faces"] > 0
    assert m["junction_boundary_edges"] == 0
    assert m["boundary_edges"] == 0
    assert m["new_non_manifold_edges"] == 0
    f = comp.surface.report["fields"]
    if name == "self_arm":
        # the arm replaced by itself: the junction faces, which both inputs share, are copied
        assert m["copied_faces"] == m["junction_faces"] and m["junction_min_angle_p05"] is None
        assert f["voxels"] == 0
    else:
        assert m["copied_faces"] == 0
        assert m["junction_min_angle_p05"] >= 20
        assert f["voxels"] > 0 and f["voxel_size"] > 0 and f["backend"] == "numpy-igl"
    assert comp.surface.report["timings"]["total"] > 0
    # every kept input face is copied exactly from its positioned input
    ids = comp.fusion_ids
    for k, cid in enumerate(ids):
        ch = comp.plan.positioned[cid]
        from rigmix.fusion.inputs import fusion_input

        x = fusion_input(ch, comp.plan.used[cid])
        sel = (surface.face_origin_input == k) & ~surface.junction_faces
        assert np.array_equal(surface.V[surface.F[sel]], x.V[x.F[surface.face_origin_face[sel]]])
