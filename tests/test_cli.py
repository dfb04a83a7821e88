"""The command line: `rigmix inspect` on real, broken and static files; `python -m rigmix.demo`."""

from __future__ import annotations

import json
import struct
import subprocess
import sys

import numpy as np
import pygltflib
import pytest
from conftest import ROOT, asset

from rigmix import examples
from rigmix.cli import build_parser, main
from rigmix.describe import describe, format_description
from rigmix.errors import InputError, UnsupportedError


def rigmix(*args, timeout=120):
    """Run ``python -m rigmix.cli ARGS`` in a fresh process."""
    return subprocess.run([sys.executable, "-m", "rigmix.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def test_inspect_every_shared_character(character_path, capsys):
    from rigmix.io import load_character

    text = rigmix("inspect", character_path)
    assert text.returncode == 0, text.stderr
    assert "Traceback" not in text.stderr
    assert "skin: yes" in text.stdout and "joints (" in text.stdout and "clips (" in text.stdout
    assert main(["inspect", str(character_path), "--json"]) == 0  # in process: one start-up less
    d = json.loads(capsys.readouterr().out)
    ch = load_character(character_path)
    c = d["counts"]
    assert c["joints"] == ch.skeleton.num_joints == len(d["joints"]) > 0
    assert c["clips"] == len(ch.clips) == len(d["clips"]) > 0
    assert c["vertices"] == sum(len(m.positions) for m in ch.meshes) + sum(len(p.mesh.positions) for p in ch.props)
    assert c["faces"] == sum(len(m.faces) for m in ch.meshes) + sum(len(p.mesh.faces) for p in ch.props)
    assert d["skinned"] is True
    assert [j["name"] for j in d["joints"]] == list(ch.skeleton.names)
    assert d["warnings"] == list(ch.warnings)
    # every joint line of the text tree is there, with its rest translation
    for name in ch.skeleton.names:
        assert f" {name}  t=(" in text.stdout
    for clip in d["clips"]:
        assert clip["channels"] > 0 and clip["duration"] >= 0 and clip["interpolations"]


def test_inspect_reports_repairs():
    d = json.loads(rigmix("inspect", asset("Wasp"), "--json").stdout)
    assert d["counts"]["warnings"] >= 1 and any("NaN" in w for w in d["warnings"])
    assert all(m["influences"] <= m["slots"] for m in d["meshes"])


def _glb_chunks(raw: bytes):
    json_len = struct.unpack_from("<I", raw, 12)[0]
    return json_len


@pytest.fixture(scope="module")
def fox_bytes():
    return asset("Fox").read_bytes()


def _assert_one_line_error(result, path, *words):
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    line = lines[0]
    assert line.startswith("rigmix: error: ") and path.name in line
    assert any(w.lower() in line.lower() for w in words), line
    assert result.stdout == ""


def test_truncated_glb(tmp_path, fox_bytes):
    path = tmp_path / "fox_truncated.glb"
    path.write_bytes(fox_bytes[: len(fox_bytes) // 2])
    _assert_one_line_error(rigmix("inspect", path), path, "truncated")
    path.write_bytes(fox_bytes[:16])  # not even a JSON chunk header
    _assert_one_line_error(rigmix("inspect", path), path, "truncated")


def test_corrupted_json_chunk(tmp_path, fox_bytes):
    json_len = _glb_chunks(fox_bytes)
    raw = bytearray(fox_bytes)
    raw[20 + json_len // 2: 20 + json_len // 2 + 8] = b"\x00}{]\xff[\"\x01"  # garbage inside the JSON
    path = tmp_path / "fox_bad_json.glb"
    path.write_bytes(bytes(raw))
    _assert_one_line_error(rigmix("inspect", path), path, "json")


def test_not_gltf(tmp_path, fox_bytes):
    path = tmp_path / "image.glb"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + fox_bytes[8:4096])  # a real file's bytes, wrong magic
    _assert_one_line_error(rigmix("inspect", path), path, "not a glTF", "glTF")
    text = tmp_path / "notes.gltf"
    text.write_text("this is not json\n")
    _assert_one_line_error(rigmix("inspect", text), text, "json", "glTF")


def test_missing_file_and_unknown_format(tmp_path):
    missing = tmp_path / "missing.glb"
    _assert_one_line_error(rigmix("inspect", missing), missing, "cannot read", "no such")
    other = tmp_path / "model.obj"
    other.write_text("v 0 0 0\n")
    _assert_one_line_error(rigmix("inspect", other), other, "format")


def _static_gltf(path):
    """A static glTF (no skin, no animation) built directly with pygltflib: a unit cube."""
    V = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float32)
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.uint16)
    vb, fb = V.tobytes(), F.tobytes()
    gltf = pygltflib.GLTF2(
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[pygltflib.Node(mesh=0, name="Cube")],
        meshes=[pygltflib.Mesh(name="Cube", primitives=[
            pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=0), indices=1)])],
        accessors=[
            pygltflib.Accessor(bufferView=0, componentType=pygltflib.FLOAT, count=len(V), type="VEC3",
                               min=V.min(0).tolist(), max=V.max(0).tolist()),
            pygltflib.Accessor(bufferView=1, componentType=pygltflib.UNSIGNED_SHORT, count=F.size, type="SCALAR"),
        ],
        bufferViews=[
            pygltflib.BufferView(buffer=0, byteOffset=0, byteLength=len(vb), target=pygltflib.ARRAY_BUFFER),
            pygltflib.BufferView(buffer=0, byteOffset=len(vb), byteLength=len(fb),
                                 target=pygltflib.ELEMENT_ARRAY_BUFFER),
        ],
        buffers=[pygltflib.Buffer(byteLength=len(vb) + len(fb))],
    )
    gltf.set_binary_blob(vb + fb)
    gltf.save_binary(str(path))
    return path


def test_static_gltf_has_no_skin(tmp_path):
    from rigmix.io import load_character
    from rigmix.io.gltf import write_gltf

    built = _static_gltf(tmp_path / "cube.glb")
    written = tmp_path / "box.glb"
    write_gltf(examples.static_box(), written)
    for path in (built, written):
        text = rigmix("inspect", path)
        assert text.returncode == 0, text.stderr
        assert "skin: none" in text.stdout and "no skin" in text.stdout
        assert "static (world)" in text.stdout  # the mesh is listed as a static prop
        d = json.loads(rigmix("inspect", path, "--json").stdout)
        assert d["skinned"] is False and d["counts"]["joints"] == 0
        assert d["counts"]["faces"] == 12 and d["counts"]["props"] == 1
        character = load_character(path)
        with pytest.raises(UnsupportedError, match=path.name):
            character.require_skinned()


def test_describe_examples_without_files():
    h = examples.humanoid()
    d = describe(h)
    assert d["counts"]["joints"] == len(examples.HUMANOID_JOINTS)
    assert d["counts"]["vertices"] == len(h.meshes[0].positions)
    assert d["counts"]["clips"] == 2 and [c["name"] for c in d["clips"]] == ["walk", "idle"]
    assert d["meshes"][0]["influences"] == 4 and d["meshes"][0]["skinned"]
    json.dumps(d)  # plain values only
    text = format_description(d)
    # the tree: each joint indented under its parent
    lines = {ln.strip().split()[0]: ln for ln in text.splitlines() if "t=(" in ln}
    indent = {name: len(ln) - len(ln.lstrip()) for name, ln in lines.items()}
    assert indent["Hand.L"] == indent["Hips"] + 12  # Hips > Spine > Chest > Shoulder > Upper > Lower > Hand
    assert indent["Spine"] == indent["Hips"] + 2 and indent["Foot.R"] == indent["Hips"] + 6
    box = describe(examples.static_box())
    assert not box["skinned"] and "skin: none" in format_description(box)


def test_main_in_process(tmp_path, capsys):
    path = tmp_path / "broken.glb"
    path.write_bytes(b"glTF" + b"\x02\x00\x00\x00")
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "broken.glb" in err
    with pytest.raises(InputError):
        main(["inspect", str(path), "--debug"])
    with pytest.raises(InputError):
        main(["--debug", "inspect", str(path)])
    args = build_parser().parse_args(["-v", "inspect", "x.glb", "--json"])
    assert args.verbose == 1 and args.json and not args.debug
    assert main([]) == 2  # no command: usage, non-zero


def test_main_in_process_leaves_the_loggers_as_it_found_them(tmp_path, caplog):
    """The command line sends rigmix's warnings to stderr while it runs; afterwards the library's
    loggers propagate to the root logger again, so an application's (or pytest's) handlers see
    them, and no handler of the command line is left behind."""
    import logging

    path = tmp_path / "broken.glb"
    path.write_bytes(b"glTF" + b"\x02\x00\x00\x00")
    before = {name: (list(logging.getLogger(name).handlers), logging.getLogger(name).level)
              for name in ("rigmix", "dfd")}
    assert main(["-v", "inspect", str(path)]) == 2
    for name, (handlers, level) in before.items():
        log = logging.getLogger(name)
        assert log.propagate and log.handlers == handlers and log.level == level
    with caplog.at_level("WARNING", logger="rigmix.animation.completion"):
        logging.getLogger("rigmix.animation.completion").warning("seen by the root logger")
    assert "seen by the root logger" in caplog.text


def test_demo_writes_and_inspects(tmp_path):
    out = tmp_path / "demo"
    r = subprocess.run([sys.executable, "-m", "rigmix.demo", "--out", str(out)],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    for name in ("Humanoid", "Quadruped"):
        assert (out / f"{name}.glb").stat().st_size > 10_000
        assert f"character {name!r}" in r.stdout
    assert "'walk'" in r.stdout and "'trot'" in r.stdout and "demo: wrote" in r.stdout
    # the contact sheet of the centaur: a PNG with the character drawn on it (not a blank page)
    import numpy as np
    from PIL import Image

    sheet = np.asarray(Image.open(out / "centaur.sheet.png").convert("L"), np.float64)
    assert sheet.shape[0] >= 480 and sheet.shape[1] >= 480
    assert (sheet < 200).mean() > 0.02, "the sheet shows nothing"
