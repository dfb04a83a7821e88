"""Fusion of the example compositions (built-in characters): the operations issue's configs.

Acceptance of the fusion issue on every config: no gap at the seams, no new non-manifold
edge, junction min-angle 5th percentile >= 20 degrees, watertight (the inputs are closed).
"""

from pathlib import Path

import numpy as np
import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


@pytest.mark.parametrize("name", ["centaur", "self_arm", "beast_arms", "tailed_humanoid"])
def test_example_fuses_cleanly(name):
    from rigmix.fusion.stage import fusion_stage
    from rigmix.pipeline import compose

    comp = compose(EXAMPLES / f"{name}.toml", until="mapping")
    comp = fusion_stage(comp)
    surface = comp.stages["surface"]
    m = comp.report["fusion"]["mesh"]
    assert m["junction_faces"] > 0
    assert m["junction_boundary_edges"] == 0
    assert m["boundary_edges"] == 0
    assert m["new_non_manifold_edges"] == 0
    f = comp.report["fusion"]["fields"]
    if name == "self_arm":
        # the arm replaced by itself: the junction faces, which both inputs share, are copied
        assert m["copied_faces"] == m["junction_faces"] and m["junction_min_angle_p05"] is None
        assert f["voxels"] == 0
    else:
        assert m["copied_faces"] == 0
        assert m["junction_min_angle_p05"] >= 20
        assert f["voxels"] > 0 and f["voxel_size"] > 0 and f["backend"] == "numpy-igl"
    assert comp.report["fusion"]["timings"]["total"] > 0
    # every kept input face is copied exactly from its positioned input
    ids = comp.stages["fusion_ids"]
    for k, cid in enumerate(ids):
        ch = comp.plan.positioned[cid]
        from rigmix.fusion.inputs import fusion_input

        x = fusion_input(ch, comp.plan.used[cid])
        sel = (surface.face_origin_input == k) & ~surface.junction_faces
        assert np.array_equal(surface.V[surface.F[sel]], x.V[x.F[surface.face_origin_face[sel]]])


def test_unknown_fusion_option_is_an_input_error():
    from rigmix.errors import InputError
    from rigmix.fusion.stage import fusion_params

    assert fusion_params(None).min_voxels_across == 32
    assert fusion_params({"min_voxels_across": 16}).min_voxels_across == 16
    with pytest.raises(InputError, match="voxels_accross"):
        fusion_params({"voxels_accross": 3})
