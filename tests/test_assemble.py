"""The output character's materials and props (issue 25): materials written once per content,
unused ones dropped; a rigid prop on a kept joint kept on that joint, one on a removed joint
dropped with a warning naming it."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from conftest import asset

from rigmix.assemble import deduplicate_materials
from rigmix.character import Material, Mesh
from rigmix.io import load_character
from rigmix.pipeline import compose

HAND = "Skeleton_arm_joint_L__2_"  # CesiumMan's left hand


def _with_prop(src: Path, dst: Path, joint: str) -> None:
    """``src`` with a 5 cm box mesh (a "staff") parented to the node ``joint``, written with pygltflib."""
    gl = pygltflib.GLTF2().load(str(src))
    blob = bytearray(gl.binary_blob())
    P = np.array([[x, y, z] for x in (-.025, .025) for y in (-.025, .025) for z in (-.025, .025)], np.float32)
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.uint16)
    views = []
    for data, target in ((P.tobytes(), pygltflib.ARRAY_BUFFER), (F.tobytes(), pygltflib.ELEMENT_ARRAY_BUFFER)):
        blob.extend(b"\0" * (-len(blob) % 4))
        views.append(len(gl.bufferViews))
        gl.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data),
                                                   target=target))
        blob.extend(data)
    gl.accessors.append(pygltflib.Accessor(bufferView=views[0], componentType=pygltflib.FLOAT, count=8,
                                           type="VEC3", min=P.min(0).tolist(), max=P.max(0).tolist()))
    gl.accessors.append(pygltflib.Accessor(bufferView=views[1], componentType=pygltflib.UNSIGNED_SHORT,
                                           count=F.size, type="SCALAR"))
    n = len(gl.accessors)
    gl.meshes.append(pygltflib.Mesh(name="staff", primitives=[pygltflib.Primitive(
        attributes=pygltflib.Attributes(POSITION=n - 2), indices=n - 1, material=0)]))
    gl.nodes.append(pygltflib.Node(name="staff", mesh=len(gl.meshes) - 1, translation=[0, 0.05, 0]))
    hand = next(i for i, node in enumerate(gl.nodes) if node.name == joint)
    gl.nodes[hand].children = list(gl.nodes[hand].children or []) + [len(gl.nodes) - 1]
    gl.buffers[0].byteLength = len(blob)
    gl.set_binary_blob(bytes(blob))
    gl.save_binary(str(dst))


@pytest.fixture(scope="module")
def cesium_with_staff(tmp_path_factory):
    folder = tmp_path_factory.mktemp("prop")
    path = folder / "CesiumStaff.glb"
    _with_prop(asset("CesiumMan"), path, HAND)
    ch = load_character(path)
    assert len(ch.props) == 1 and ch.skeleton.names[ch.props[0].joint] == HAND
    return path


def _config(folder: Path, body: Path, target_joint: str, source_joint: str) -> Path:
    cfg = folder / f"swap_{target_joint}.toml"
    cfg.write_text(f'name = "staff"\n[characters.body]\npath = "{body}"\n'
                   f'[characters.figure]\npath = "{asset("RiggedFigure")}"\n'
                   f'[[actions]]\nop = "replace"\nsource = "figure"\nsource_joint = "{source_joint}"\n'
                   f'target = "body"\ntarget_joint = "{target_joint}"\n')
    return cfg


def test_prop_on_a_kept_joint_stays_on_it(cesium_with_staff, tmp_path):
    from rigmix.io.gltf import write_gltf

    comp = compose(_config(tmp_path, cesium_with_staff, "Skeleton_arm_joint_R", "arm_joint_R_1"))
    ch = comp.character
    assert len(ch.props) == 1
    assert ch.skeleton.names[ch.props[0].joint] == HAND
    # it still follows the hand in the written file, at the same place at rest
    write_gltf(ch, tmp_path / "out.glb")
    back = load_character(tmp_path / "out.glb")
    assert len(back.props) == 1 and back.skeleton.names[back.props[0].joint] == HAND
    src = load_character(cesium_with_staff)
    w_in = src.skeleton.rest_worlds()[src.props[0].joint] @ src.props[0].matrix
    w_out = back.skeleton.rest_worlds()[back.props[0].joint] @ back.props[0].matrix
    assert np.allclose(w_in[:3, 3], w_out[:3, 3], atol=1e-4)


def test_prop_on_a_removed_joint_is_dropped_with_a_warning(cesium_with_staff, tmp_path):
    comp = compose(_config(tmp_path, cesium_with_staff, "Skeleton_arm_joint_L__4_", "arm_joint_L_1"))
    ch = comp.character
    assert ch.props == ()
    assert any("prop 'staff'" in w and HAND in w for w in ch.warnings), ch.warnings


def test_materials_are_written_once_and_only_when_used():
    """centaur: the Knight and the Horse both carry materials equal in all but name."""
    asset("Horse"), asset("Knight")
    comp = compose(Path(__file__).parent / "configs" / "centaur.toml")
    ch = comp.character
    keys = [(m.base_color.tobytes(), m.metallic, m.roughness, m.base_color_texture) for m in ch.materials]
    assert len(set(keys)) == len(keys)
    used = {m.material for m in ch.meshes} | {p.mesh.material for p in ch.props}
    assert used == set(range(len(ch.materials)))
    assert len(ch.materials) < sum(len(c.materials) for c in comp.inputs.values())


def test_deduplicate_materials_remaps_meshes():
    a, b, c = Material("Black", np.array([0, 0, 0, 1.0])), Material("Black.001", np.array([0, 0, 0, 1.0])), \
        Material("Red", np.array([1, 0, 0, 1.0]))
    tri = dict(positions=np.eye(3), faces=np.array([[0, 1, 2]]))
    meshes = [Mesh("m0", material=1, **tri), Mesh("m1", material=0, **tri), Mesh("m2", material=-1, **tri)]
    out, props, mats = deduplicate_materials(meshes, [], [a, b, c])
    assert [m.name for m in mats] == ["Black"]  # Red unused, Black.001 equal to Black
    assert [m.material for m in out] == [0, 0, -1]
    assert struct.pack("4d", *mats[0].base_color) == struct.pack("4d", 0, 0, 0, 1)
