"""Mirroring a rigged character (rigmix.operations.mirror) and the config's ``mirror`` key, on real characters."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import asset, corpus

from rigmix.animation import clip_times, sample_clip
from rigmix.config import parse_config
from rigmix.errors import InputError
from rigmix.io import load_character
from rigmix.operations.mirror import MirrorPlane, mirror_character, mirror_plane, swap_side
from rigmix.skinning import rest_pose, skin_character

# CesiumMan: a Z-up anchor above its root and a one-sided name ("arm_joint_L__4_");
# Horse: five roots without anchor (the plane's offset goes into their keys); Fox: Left/Right words.
CHARACTERS = ("CesiumMan", "Horse", "Fox")


@pytest.fixture(scope="module")
def loaded():
    return {name: load_character(asset(name)) for name in CHARACTERS}


def _diag(character):
    """Bounding-box diagonal of the rest pose (the Horse's bind space is in other units)."""
    V = np.concatenate(rest_pose(character))
    return float(np.linalg.norm(np.ptp(V, axis=0)))


@pytest.mark.parametrize("name, other", [
    ("UpperArm.L", "UpperArm.R"), ("arm_joint_L__4_", "arm_joint_R__4_"), ("b_LeftUpperArm_09", "b_RightUpperArm_09"),
    ("L_Hand", "R_Hand"), ("hand_left", "hand_right"), ("leg_L1", "leg_R1"),
    ("mixamorig:LeftHand", "mixamorig:RightHand"),
    ("upperarm_l", "upperarm_r"), ("Spine_L_R", "Spine_R_L"), ("LEFT_ARM", "RIGHT_ARM"),
])
def test_swap_side_conventions(name, other):
    assert swap_side(name) == other
    assert swap_side(other) == name


@pytest.mark.parametrize("name", ["Root", "Hips", "upright", "Tail1", "Leg", "Rleg", "LowerArm", "b_Neck_04"])
def test_swap_side_leaves_names_without_a_side(name):
    assert swap_side(name) == name


@pytest.mark.parametrize("name", CHARACTERS)
def test_skinned_mirror_is_the_reflection_at_every_frame(loaded, name):
    """Skinned with its own (mirrored) clips, every vertex at every frame is the reflected vertex."""
    c = loaded[name]
    diag = _diag(c)
    # the detected plane, and an off-centre y plane (exercises the offset on roots and anchors)
    for plane in (mirror_plane(c), MirrorPlane(1, 0.3 * diag)):
        m = mirror_character(c, plane)
        assert len(m.clips) == len(c.clips) >= 1
        for clip, mclip in zip(c.clips, m.clips):
            t = clip_times(clip)
            original = skin_character(c, *sample_clip(c.skeleton, clip, t))
            mirrored = skin_character(m, *sample_clip(m.skeleton, mclip, t))
            for a, b in zip(original, mirrored):
                assert a.shape == b.shape and a.shape[0] == len(t)
                assert np.abs(plane.reflect(a) - b).max() <= 1e-5 * diag
        # local rotations stay proper (a reflection matrix would not be a glTF rotation)
        R = m.skeleton.rest_worlds()[:, :3, :3]
        assert np.all(np.linalg.det(R) > 0)


@pytest.mark.parametrize("name", CHARACTERS)
def test_mirror_twice_is_the_original(loaded, name):
    c = loaded[name]
    plane = mirror_plane(c)
    back = mirror_character(mirror_character(c, plane), plane)
    assert back.skeleton.names == c.skeleton.names
    # completion tells a mirrored copy of an asset from a second copy by the flag
    assert mirror_character(c, plane).mirrored and not back.mirrored and not c.mirrored
    for attr in ("translations", "rotations", "scales", "inverse_binds", "parents"):
        np.testing.assert_allclose(getattr(back.skeleton, attr), getattr(c.skeleton, attr), atol=1e-9)
    for a, b in zip(c.skeleton.anchors, back.skeleton.anchors):
        np.testing.assert_allclose(b.matrix, a.matrix, atol=1e-9)
    for a, b in zip(c.meshes, back.meshes):
        np.testing.assert_allclose(b.positions, a.positions, atol=1e-9)
        np.testing.assert_array_equal(b.faces, a.faces)
        np.testing.assert_array_equal(b.joints, a.joints)
        np.testing.assert_array_equal(b.weights, a.weights)
        if a.normals is not None:
            np.testing.assert_allclose(b.normals, a.normals, atol=1e-12)
    for ca, cb in zip(c.clips, back.clips):
        assert ca.name == cb.name
        for ta, tb in zip(ca.tracks, cb.tracks):
            assert (ta.joint, ta.path, ta.interpolation) == (tb.joint, tb.path, tb.interpolation)
            np.testing.assert_allclose(tb.values, ta.values, atol=1e-9)
    # the plane detected on the mirrored character is the same plane
    again = mirror_plane(mirror_character(c, plane))
    assert again.axis == plane.axis
    assert abs(again.offset - plane.offset) <= 1e-3 * _diag(c)


def test_mirror_swaps_sides_and_faces(loaded):
    """The mirrored Horse's left legs are the original right legs, reflected onto the left side,
    with outward faces and normals."""
    c = loaded["Horse"]
    plane = mirror_plane(c)
    assert plane.axis == 0 and plane.error < 0.01  # the Horse faces +Z: left/right is x
    m = mirror_character(c, plane)
    P, Pm = c.skeleton.rest_worlds()[:, :3, 3], m.skeleton.rest_worlds()[:, :3, 3]
    diag = _diag(c)
    for side in ("FrontUpperLeg", "BackUpperLeg", "Ear1"):
        jl, jr = c.skeleton.index(f"{side}.L"), c.skeleton.index(f"{side}.R")
        assert m.skeleton.names[jr] == f"{side}.L"  # the right leg, now named left...
        np.testing.assert_allclose(Pm[jr], plane.reflect(P[jr]), atol=1e-9)
        assert np.linalg.norm(Pm[jr] - P[jl]) < 0.02 * diag  # ...stands where the left leg stood
        assert np.sign(Pm[jr][0] - plane.offset) == np.sign(P[jl][0] - plane.offset)
    for a, b in zip(c.meshes, m.meshes):
        if a.normals is None:
            continue
        V, F = b.positions, b.faces
        fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        ok = np.linalg.norm(fn, axis=1) > 1e-12
        # winding agrees with the stored normals exactly as often as in the original
        def agree(mesh):
            Vx, Fx = mesh.positions, mesh.faces
            g = np.cross(Vx[Fx[:, 1]] - Vx[Fx[:, 0]], Vx[Fx[:, 2]] - Vx[Fx[:, 0]])
            return np.einsum("fk,fk->f", g[ok], mesh.normals[Fx[ok]].sum(axis=1)) > 0
        np.testing.assert_array_equal(agree(b), agree(a))
        assert agree(a).mean() > 0.9


def test_mirror_plane_axis_names(loaded):
    c = loaded["CesiumMan"]
    assert mirror_plane(c, "y").axis == 1
    with pytest.raises(InputError, match="axis"):
        mirror_plane(c, "w")


def test_config_mirror_key():
    base = {"characters": {"a": {"path": "builtin:humanoid"}}}
    for value, expected in ((True, True), ("x", "x"), ("z", "z"), (False, False)):
        cfg = parse_config({"characters": {"a": {"path": "builtin:humanoid", "mirror": value}}})
        assert cfg.characters["a"].mirror == expected
    assert parse_config(base).characters["a"].mirror is False
    for bad in ("w", 1, "yes"):
        with pytest.raises(InputError, match=r"characters\.a\.mirror"):
            parse_config({"characters": {"a": {"path": "builtin:humanoid", "mirror": bad}}})


def test_compose_puts_the_mirrored_right_arm_on_the_left(tmp_path):
    """``mirror = true`` end to end: the Knight's left arm replaced by its own right arm, mirrored."""
    from rigmix.pipeline import compose

    path = asset("Knight")
    cfg = tmp_path / "mirrored_arm.toml"
    cfg.write_text(f"""
name = "mirrored_arm"
[characters.body]
path = "{path}"
[characters.donor]
path = "{path}"
mirror = true
[[actions]]
op = "replace"
source = "donor"
source_joint = "UpperArm.L"
target = "body"
target_joint = "UpperArm.L"
[weights]
feature_field = false
""")
    comp = compose(cfg)
    from rigmix.skinning import rest_at_bind

    original, donor = rest_at_bind(load_character(path)), comp.inputs["donor"]  # composed in the bind pose
    plane = mirror_plane(original)
    # the donor is the mirrored Knight: its "UpperArm.L" is the original right arm, reflected
    jr = original.skeleton.index("UpperArm.R")
    assert donor.skeleton.names[jr] == "UpperArm.L"
    np.testing.assert_allclose(donor.skeleton.rest_worlds()[jr, :3, 3],
                               plane.reflect(original.skeleton.rest_worlds()[jr, :3, 3]), atol=1e-9)
    # the output's left arm joints come from the donor, on the left side of the body
    out = comp.character
    prov = comp.plan.provenance
    from_donor_joints = [donor.skeleton.names[prov[o][0][1]] for o in range(out.skeleton.num_joints)
                         if prov[o][0][0] == "donor"]
    assert "LowerArm.L" in from_donor_joints  # the subtree below the fused UpperArm.L
    # exactly the original right arm below the shoulder (the Knight's right thumb is misnamed
    # "Thumb.L" in the file, so the mirrored one is "Thumb.R": names swap, they are not guessed)
    right = original.skeleton.subtree(jr)
    right[jr] = False
    assert sorted(from_donor_joints) == sorted(donor.skeleton.names[k] for k in np.flatnonzero(right))
    surface = comp.surface
    ids = list(comp.fusion_ids)
    from_donor = np.asarray(surface.origin_input) == ids.index("donor")
    assert from_donor.sum() > 50
    left = np.sign(original.skeleton.rest_worlds()[original.skeleton.index("UpperArm.L"), 0, 3] - plane.offset)
    assert np.mean(np.sign(surface.V[from_donor, 0] - plane.offset) == left) > 0.99
    # weight invariants on the written character
    for mesh in out.meshes:
        if mesh.skinned:
            assert np.all(mesh.weights >= 0)
            np.testing.assert_allclose(mesh.weights.sum(axis=1), 1.0, atol=1e-6)
            assert mesh.weights.shape[1] <= 4 or np.count_nonzero(mesh.weights, axis=1).max() <= 4
    assert comp.report["weights"]["max_influences"] <= 4


def test_a_limb_replaced_by_its_mirror_on_a_symmetric_body_needs_no_junction(tmp_path):
    """PlatformerCharacter is symmetric: its left arm mirrored meets the body's right shoulder
    edge to edge, no seam is left open, and the junction is empty (no faces picked from the
    inputs in its place). The output has the input's borders and nothing more."""
    from benchmarks.corpus_matrix import load_subjects, mirror_cases, write_configs
    from rigmix.fusion.meshutil import edge_counts
    from rigmix.geometry import weld
    from rigmix.pipeline import compose

    corpus("PlatformerCharacter")
    name = "mirror__PlatformerCharacter__UpperArm.R"
    case = next(c for c in mirror_cases(load_subjects(["PlatformerCharacter"])) if c.name == name)
    comp = compose(write_configs([case], tmp_path)[name], until="fusion")
    m = comp.report["mesh"]
    assert m["junction_faces"] == 0
    assert not any(g.get("fallback") for g in comp.report["fields"]["grids"])
    for key in ("junction_boundary_edges", "open_seam_edges", "new_non_manifold_edges"):
        assert m[key] == 0, key
    body = comp.inputs["body"]
    V = np.concatenate([x.positions for x in body.meshes])
    offsets = np.cumsum([0] + [len(x.positions) for x in body.meshes])
    F = np.concatenate([np.asarray(x.faces) + o for x, o in zip(body.meshes, offsets)])
    _, counts_in = edge_counts(weld(V, F)[2])
    _, counts_out = edge_counts(weld(comp.surface.V, comp.surface.F)[2])
    assert (counts_out == 1).sum() == (counts_in == 1).sum()


def test_a_seam_that_runs_into_a_hole_of_the_mesh_closes_it(tmp_path):
    """The Deer's tail is cut next to a hole of its mesh: the seam runs into the hole, a chain
    and no loop, which the junction cannot bridge (it was left open, 7 to 10 boundary edges).
    Closed along the hole's edge, it is bridged like any seam: no gap, no crossing."""
    from benchmarks.corpus_matrix import load_subjects, tail_cases, write_configs
    from rigmix.pipeline import compose

    corpus("Deer")
    corpus("CyberpunkCharacter")
    name = "tail__CyberpunkCharacter__Deer"
    case = next(c for c in tail_cases(load_subjects(["CyberpunkCharacter", "Deer"])) if c.name == name)
    m = compose(write_configs([case], tmp_path)[name], until="fusion").report["mesh"]
    assert m["junction_faces"] > 0
    for key in ("open_seam_edges", "junction_boundary_edges", "new_non_manifold_edges", "junction_self_intersections"):
        assert m[key] == 0, key


def test_a_seam_closed_along_a_hole_the_isosurface_misses_stays_open_and_counted(tmp_path):
    """The Stegosaurus' neck seam runs into a slit of its mesh; closed along it, no isosurface
    loop matches it, and the whole cluster would be picked from the inputs (104 crossing pairs,
    triangles down to 3 degrees). The junction is made without it: the seam stays open, counted
    in open_seam_edges, and the rest of the junction is clean. That gate failed, the fusion runs
    again with the Stegosaurus' neck taken whole (``retry_whole_region``), and closes; the first
    fusion is the report's ``rejected_attempt``."""
    from benchmarks.corpus_matrix import head_swap_cases, load_subjects, write_configs
    from rigmix.gates import failed_mesh_gates
    from rigmix.pipeline import compose

    corpus("Stegosaurus")
    corpus("Trex")
    name = "head_swap__Stegosaurus__Trex"
    case = next(c for c in head_swap_cases(load_subjects(["Stegosaurus", "Trex"])) if c.name == name)
    path = write_configs([case], tmp_path)[name]
    # the Trex head at the chains' ratio (1.012; scale = "auto" takes the necks' cut, 0.641, where
    # the seam misses the slit): the seam of that junction runs into it
    text = path.read_text()
    assert 'scale = "auto"' in text
    path.write_text(text.replace('scale = "auto"', "scale = 1.012", 1))
    m = compose(path, until="fusion").report["mesh"]
    assert m["replaced_whole_region"] is True and m["open_seam_edges"] == m["junction_boundary_edges"] == 0
    assert not failed_mesh_gates(m)
    # the first fusion, not kept (the report's rejected_attempt)
    first = m["rejected_attempt"]
    grids = first["fields"]["grids"]
    assert not any(g.get("fallback") for g in grids) and any(g.get("seams_left_open") for g in grids)
    assert first["mesh"]["replaced_whole_region"] is False and "rejected_attempt" not in first["mesh"]
    f = first["mesh"]
    assert f["open_seam_edges"] == f["junction_boundary_edges"] > 0  # the gap is reported, not hidden
    assert f["junction_self_intersections"] == 0 and f["junction_min_angle_p05"] >= 20.0
    assert set(first["failed_gates"]) == set(failed_mesh_gates(f)) >= {"open_seam_edges", "junction_boundary_edges"}
