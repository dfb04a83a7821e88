"""Identity compositions of real characters through the whole pipeline: a limb replaced by
itself gives back the input, face for face, and passes the mesh and identity gates.

The donor is measured as the body is (at rest in world space), so its scale is exactly 1 and its
positions are the body's bit for bit: the faces both share are recognised and copied once.

The fused joint is kept by both inputs (the output's one joint stands for the target's and the
source's), so whatever is skinned to it alone has presence 1 in both: part of the upper arm of
a many-primitive humanoid, shoulder pads and sleeves that are parts of their own, a robot's
rigid leg parts, a whole crab on its root joint. Each such face must come back once
(:func:`rigmix.fusion.seams.shared_preserved`), not once per input beside itself.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from conftest import asset, corpus

from rigmix.gates import IDENTITY_TOLERANCE

#: case -> (corpus character, the fused joints: a limb and, for a robot, its detached IK foot)
CASES = {
    # 10 primitives, split at UV seams; shoulder pads and sleeve parts skinned to UpperArm.L alone
    "cyberpunk_arm": ("CyberpunkCharacter", ("UpperArm.L",)),
    # a robot of 9 part meshes on one skin; the leg's rigid parts on Leg1.L and on the IK foot
    "enemy_large_leg": ("EnemyLarge", ("Leg1.L", "Foot.L")),
    # a leaf joint: no limb length, the donor's scale is the ratio of two mesh sizes, which must
    # come out exactly 1 for the positions (and so the faces) to stay bit for bit the same
    "enemy_large_head": ("EnemyLarge", ("Head",)),
    # copied faces meet the other input's kept faces along chains running into open borders:
    # no seam left open there, the other input closes it
    "rat_front_leg": ("Rat", ("FrontUpLeg.L",)),
    # a blink: the Eye's Run clip scales through zero (a negative key scale); replayed, not clamped
    "enemy_two_legs_head": ("EnemyTwoLegs", ("Head",)),
}


def identity_config(tmp_path, name: str, character: str, joints) -> str:
    """A config replacing ``joints`` of a corpus character by the same joints of a second copy."""
    path = corpus(character)
    text = f'name = "{name}"\n'
    for cid in ("body", "donor"):
        text += f'[characters.{cid}]\npath = "{path.as_posix()}"\n'
    for j in joints:
        text += (f'[[actions]]\nop = "replace"\nsource = "donor"\nsource_joint = "{j}"\n'
                 f'target = "body"\ntarget_joint = "{j}"\nmode = "blend"\n')
    cfg = tmp_path / f"{name}.toml"
    cfg.write_text(text)
    return cfg


def canonical_faces(V, F):
    """Faces as rows of their nine corner coordinates, sorted (a multiset, order-free)."""
    T = np.asarray(V, np.float64)[np.asarray(F, np.int64)].reshape(len(F), 9)
    return T[np.lexsort(T.T[::-1])]


@pytest.mark.parametrize("case", sorted(CASES))
def test_identity_composition_gives_back_every_face_once(case, tmp_path):
    from rigmix.export import write_outputs
    from rigmix.fusion.meshutil import nondegenerate
    from rigmix.pipeline import compose

    character, joints = CASES[case]
    comp = compose(identity_config(tmp_path, case, character, joints))
    write_outputs(comp, glb=tmp_path / "out.glb", report=tmp_path / "out.json")
    report = json.loads((tmp_path / "out.json").read_text())
    mesh = report["mesh"]
    assert mesh["new_non_manifold_edges"] == 0
    assert mesh["junction_boundary_edges"] == 0 and mesh["open_seam_edges"] == 0
    gates = {g["name"]: g for g in report["gates"]}
    for name in ("new_non_manifold_edges", "junction_boundary_edges", "open_seam_edges",
                 "identity_surface_error", "identity_skinned_error"):
        assert gates[name]["pass"] is True, gates[name]
    assert gates["identity_surface_error"]["value"] <= IDENTITY_TOLERANCE

    # every face of the input (collapsed faces aside) comes back exactly once, none beside it
    body = comp.fusion_inputs[comp.fusion_ids.index("body")]
    keep = nondegenerate(body.F)
    out = comp.surface
    assert len(out.F) == int(keep.sum())
    assert np.array_equal(canonical_faces(out.V, out.F), canonical_faces(body.V, body.F[keep]))
    assert np.all(out.face_origin_input >= 0)  # copied from the inputs, nothing generated


def split_weight_seams(character) -> int:
    """Pairs of input vertices at one rest position whose weights differ (glTF seam copies)."""
    from scipy.spatial import cKDTree

    from rigmix.quality import skinned_surface
    from rigmix.skinning import linear_blend_skinning, rest_skinning_matrices

    V, _, J, W = skinned_surface(character)
    R = linear_blend_skinning(V, J, W, rest_skinning_matrices(character.skeleton))
    tol = 1e-7 * np.linalg.norm(R.max(axis=0) - R.min(axis=0))
    pairs = cKDTree(R).query_pairs(tol, output_type="ndarray")
    dense = np.zeros((len(V), len(character.skeleton.names)))
    for k in range(J.shape[1]):
        np.add.at(dense, (np.arange(len(V)), J[:, k]), W[:, k])
    return int((np.abs(dense[pairs[:, 0]] - dense[pairs[:, 1]]).sum(axis=1) > 0.05).sum())


def test_identity_errors_compare_a_split_vertex_with_its_own_copy():
    """A character against a copy of itself moved by rounding noise (as writing a file does) is
    exact, even where glTF seam copies at one position carry different weights: the Apatosaurus
    has such pairs, and the closest input face may belong to the other copy. A vertex whose
    weights did change is still found."""
    from rigmix.io.gltf import read_gltf
    from rigmix.quality import identity_errors
    from rigmix.skinning import rest_at_bind

    character = rest_at_bind(read_gltf(corpus("Apatosaurus")))  # as compose reads it
    assert split_weight_seams(character) > 0  # the case this test is about exists
    rng = np.random.default_rng(0)

    def rounded(mesh, joints=None, weights=None):
        P = np.asarray(mesh.positions, np.float64)
        noise = rng.normal(scale=1e-8 * np.linalg.norm(P.max(axis=0) - P.min(axis=0)), size=P.shape)
        return replace(mesh, positions=P + noise, joints=mesh.joints if joints is None else joints,
                       weights=mesh.weights if weights is None else weights)

    clips = [(c, c) for c in character.clips]
    copy = replace(character, meshes=tuple(rounded(m) if m.skinned else m for m in character.meshes))
    same = identity_errors(character, copy, clips)
    assert same["frames"] > 0
    assert same["surface_error"] < 1e-6 and same["skinned_error"] < 1e-6

    # the vertex farthest from the root at bind, re-bound to the root: it stops following its limb
    mesh = next(m for m in character.meshes if m.skinned)
    root = np.linalg.inv(character.skeleton.inverse_binds[0])[:3, 3]
    moving = int(np.argmax(np.linalg.norm(np.asarray(mesh.positions) - root, axis=1)))
    joints, weights = np.array(mesh.joints), np.array(mesh.weights, np.float64)
    joints[moving] = 0
    weights[moving] = (1.0,) + (0.0,) * (weights.shape[1] - 1)
    changed = replace(character, meshes=tuple(rounded(m, joints, weights) if m is mesh else m
                                              for m in character.meshes))
    assert identity_errors(character, changed, clips)["skinned_error"] > IDENTITY_TOLERANCE


def test_coarse_mesh_identity_measures_its_junction_stretch(tmp_path):
    """SimpleSkin's 10 vertices lie farther from its joints than its copied junction reaches:
    the stretch band still holds the nearest vertex, so the gate is measured (1 for a copy)."""
    from rigmix.export import write_outputs
    from rigmix.pipeline import compose

    cfg = tmp_path / "simple.toml"
    path = asset("SimpleSkin").as_posix()
    cfg.write_text(f'[characters.body]\npath = "{path}"\n[characters.donor]\npath = "{path}"\n'
                   '[[actions]]\nop = "replace"\nsource = "donor"\nsource_joint = "joint_2"\n'
                   'target = "body"\ntarget_joint = "joint_2"\nmode = "blend"\n')
    comp = compose(cfg)
    write_outputs(comp, glb=tmp_path / "out.glb", report=tmp_path / "out.json")
    gates = {g["name"]: g for g in json.loads((tmp_path / "out.json").read_text())["gates"]}
    assert gates["junction_stretch_ratio"]["value"] is not None
    assert all(g["pass"] for g in gates.values()), [g for g in gates.values() if not g["pass"]]
