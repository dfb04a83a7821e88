"""Hostile inputs to the readers (issue 23, findings 1 and 10): no file outside the asset's folder
is ever opened, nothing but regular files is read, sizes are checked before reading, and
out-of-spec glTF is refused or repaired with a warning.

The hostile files are built here from ``tiny_skinned`` (tests/test_bad_inputs.py) under
``tmp_path``: the character in ``tmp_path/asset/``, a sentinel file holding valid buffer bytes
beside it in ``tmp_path`` (so that a reader that followed the URI would load it without error).
Whether a file is opened is checked with an audit hook on ``open`` in a subprocess.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import textwrap
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pytest
from conftest import ROOT
from test_bad_inputs import glb_bytes, tiny_skinned

from rigmix.cli import main as cli_main
from rigmix.errors import InputError, UnsupportedError
from rigmix.io import accessors, gltf_materials, load_character
from rigmix.io.gltf import read_gltf

PNG = (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + struct.pack(">IIBBBBB", 1, 1, 8, 2, 0, 0, 0)
       + b"\0" * 4 + struct.pack(">I", 0) + b"IEND" + b"\xaeB`\x82")


def _gltf(tmp_path: Path, uri=None, mutate=None) -> tuple[Path, Path, dict, bytes]:
    """``tmp_path/asset/c.gltf`` whose buffer is read from ``uri`` (default: ``c.bin`` beside it)
    and the sentinel ``tmp_path/secret.bin`` (the same valid bytes); returns both paths, the
    JSON and the bytes."""
    gl, data = tiny_skinned()
    data = data + b"\0" * (-len(data) % 4)
    folder = tmp_path / "asset"
    folder.mkdir(exist_ok=True)
    (folder / "c.bin").write_bytes(data)
    secret = tmp_path / "secret.bin"
    secret.write_bytes(data)
    gl["buffers"][0]["uri"] = "c.bin" if uri is None else uri
    if mutate is not None:
        mutate(gl, folder, secret)
    path = folder / "c.gltf"
    path.write_text(json.dumps(gl))
    return path, secret, gl, data


def _assert_clean_refusal(exc: BaseException, tmp_path: Path, secret: Path) -> None:
    """One line that names neither the outside path nor the sentinel's size."""
    msg = str(exc)
    assert "\n" not in msg
    assert str(tmp_path) not in msg and "secret" not in msg
    assert str(secret.stat().st_size) not in msg


def _opened_while_reading(path: Path, tmp_path: Path) -> tuple[list[str], str]:
    """Read ``path`` in a subprocess with an audit hook on ``open``: the files opened under
    ``tmp_path`` or in /dev (real paths), and the error line (or "ok")."""
    script = textwrap.dedent(f"""
        import json, os, sys
        from rigmix.errors import RigmixError
        from rigmix.io import load_character
        import rigmix.io.gltf, rigmix.io.usd_read  # imports done before the hook
        opened = []
        def hook(event, args):
            if event == "open" and isinstance(args[0], (str, bytes)):
                p = os.fsdecode(args[0])
                opened.append(os.path.realpath(p))
        sys.addaudithook(hook)
        try:
            load_character({str(path)!r})
            result = "ok"
        except RigmixError as exc:
            result = str(exc)
        watch = (os.path.realpath({str(tmp_path)!r}), "/dev")
        print(json.dumps([[p for p in opened if p.startswith(watch)], result]))
    """)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    opened, result = json.loads(out.stdout.strip().splitlines()[-1])
    return opened, result


def _hostile_uri(case: str, tmp_path: Path):
    """(uri, mutate) for each way of pointing a URI outside the folder or at a non-file."""
    secret = str(tmp_path / "secret.bin")

    def link(name, target):
        def mutate(gl, folder, _):
            os.symlink(target, folder / name)
        return mutate

    def fifo(gl, folder, _):
        os.mkfifo(folder / "pipe.bin")

    def directory(gl, folder, _):
        (folder / "dir.bin").mkdir()

    return {
        "dotdot": ("../secret.bin", None),
        "deep_dotdot": ("sub/../../secret.bin", None),
        "absolute": (secret, None),
        "file_scheme": ("file://" + secret, None),
        "percent_dotdot": ("%2e%2e/secret.bin", None),
        "percent_absolute": (quote(secret, safe=""), None),
        "symlink_out": ("link.bin", link("link.bin", secret)),
        "symlink_dir_out": ("up/secret.bin", link("up", str(tmp_path))),
        "dev_zero_symlink": ("zero.bin", link("zero.bin", "/dev/zero")),
        "fifo": ("pipe.bin", fifo),
        "directory": ("dir.bin", directory),
    }[case]


HOSTILE = ["dotdot", "deep_dotdot", "absolute", "file_scheme", "percent_dotdot", "percent_absolute",
           "symlink_out", "symlink_dir_out", "dev_zero_symlink", "fifo", "directory"]


# --------------------------------------------------------------------------- finding 1: confinement


def test_buffer_inside_the_folder_reads(tmp_path):
    path, *_ = _gltf(tmp_path)
    assert read_gltf(path).skeleton.names == ("j0", "j1", "j2")
    link, *_ = _gltf(tmp_path, "alias.bin", lambda gl, folder, _: os.symlink("c.bin", folder / "alias.bin"))
    assert read_gltf(link).skeleton.names == ("j0", "j1", "j2")  # a symlink that stays inside is fine


@pytest.mark.parametrize("case", HOSTILE)
def test_hostile_buffer_uri_is_refused(case, tmp_path):
    uri, mutate = _hostile_uri(case, tmp_path)
    path, secret, *_ = _gltf(tmp_path, uri, mutate)
    with pytest.raises(InputError, match=r"c\.gltf: buffers\[0\]") as exc:
        read_gltf(path)
    _assert_clean_refusal(exc.value, tmp_path, secret)


@pytest.mark.parametrize("case", ["dotdot", "absolute", "percent_absolute", "symlink_out", "dev_zero_symlink",
                                  "fifo"])
def test_hostile_uri_never_opens_the_outside_file(case, tmp_path):
    uri, mutate = _hostile_uri(case, tmp_path)
    path, secret, *_ = _gltf(tmp_path, uri, mutate)
    opened, result = _opened_while_reading(path, tmp_path)
    assert result.startswith("c.gltf: buffers[0]")
    folder = os.path.realpath(path.parent)
    outside = [p for p in opened if os.path.commonpath([folder, p]) != folder]
    assert outside == []
    assert os.path.realpath(path) in opened  # the hook saw the reader's own opens


def test_outside_image_is_refused_not_embedded(tmp_path):
    """An absolute image URI used to embed that PNG in the output."""
    (tmp_path / "secret.png").write_bytes(PNG)

    def image(gl, folder, _):
        gl["images"] = [{"uri": str(tmp_path / "secret.png")}]
        gl["textures"] = [{"source": 0}]
        gl["materials"] = [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]

    path, secret, *_ = _gltf(tmp_path, mutate=image)
    with pytest.raises(InputError, match=r"images\[0\] has an absolute") as exc:
        read_gltf(path)
    _assert_clean_refusal(exc.value, tmp_path, secret)


def test_missing_image_inside_the_folder_drops_the_texture(tmp_path):
    def image(gl, folder, _):
        gl["images"] = [{"uri": "missing.png"}, {"uri": "ok.png"}]
        gl["textures"] = [{"source": 0}, {"source": 1}]
        gl["materials"] = [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}},
                           {"pbrMetallicRoughness": {"baseColorTexture": {"index": 1}}}]
        (folder / "ok.png").write_bytes(PNG)

    c = read_gltf(_gltf(tmp_path, mutate=image)[0])
    assert c.materials[0].base_color_texture is None
    assert any("'missing.png' was not found" in w for w in c.warnings)
    assert c.materials[1].base_color_texture.data == PNG


def test_image_larger_than_the_limit_is_refused_before_reading(tmp_path, monkeypatch):
    def image(gl, folder, _):
        gl["images"] = [{"uri": "big.png"}]
        gl["textures"] = [{"source": 0}]
        gl["materials"] = [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]
        (folder / "big.png").write_bytes(PNG + b"\0" * 1000)

    path = _gltf(tmp_path, mutate=image)[0]
    monkeypatch.setattr(gltf_materials, "MAX_IMAGE_BYTES", 512)
    with pytest.raises(InputError, match=r"images\[0\] \('big.png'\) has 1\d+ bytes, more than the 512-byte limit"):
        read_gltf(path)


def test_data_uri_longer_than_its_byte_length_is_refused_before_decoding(tmp_path):
    import base64

    def data_uri(gl, folder, secret):
        payload = base64.b64encode(secret.read_bytes() * 1000).decode()
        gl["buffers"][0]["uri"] = "data:application/octet-stream;base64," + payload

    path, *_ = _gltf(tmp_path, mutate=data_uri)
    with pytest.raises(InputError, match=r"buffers\[0\]: data URI of \d+ characters is longer than"):
        read_gltf(path)


def test_exact_data_uri_reads(tmp_path):
    import base64

    def data_uri(gl, folder, secret):
        payload = base64.b64encode(secret.read_bytes()).decode()
        gl["buffers"][0]["uri"] = "data:application/octet-stream;base64," + payload

    assert read_gltf(_gltf(tmp_path, mutate=data_uri)[0]).skeleton.names == ("j0", "j1", "j2")


def _run_inspect(path: Path, tmp_path: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "rigmix.cli", "inspect", str(path)], capture_output=True,
                          text=True, timeout=60, env=env, cwd=tmp_path)


@pytest.mark.parametrize("kind", ["dev_zero", "fifo", "directory"])
def test_input_file_must_be_a_regular_file(kind, tmp_path):
    """``inspect`` of a .glb that is /dev/zero (via a symlink), a FIFO or a folder fails at once
    (it used to read /dev/zero until memory ran out, and block on the FIFO)."""
    path = tmp_path / "c.glb"
    if kind == "dev_zero":
        os.symlink("/dev/zero", path)
    elif kind == "fifo":
        os.mkfifo(path)
    else:
        path.mkdir()
    out = _run_inspect(path, tmp_path)
    assert out.returncode == 2, out.stderr
    assert "not a regular file" in out.stderr and len(out.stderr.strip().splitlines()) == 1


def test_input_symlink_to_a_regular_file_reads(tmp_path):
    gl, data = tiny_skinned()
    (tmp_path / "real.glb").write_bytes(glb_bytes(gl, data))
    os.symlink("real.glb", tmp_path / "c.glb")
    assert read_gltf(tmp_path / "c.glb").skeleton.names == ("j0", "j1", "j2")


def test_input_file_size_is_capped_before_reading(tmp_path, monkeypatch):
    gl, data = tiny_skinned()
    (tmp_path / "c.glb").write_bytes(glb_bytes(gl, data))
    monkeypatch.setattr(accessors, "MAX_FILE_BYTES", 100)
    with pytest.raises(InputError, match=r"c\.glb: the file has \d+ bytes, more than the 100-byte limit"):
        read_gltf(tmp_path / "c.glb")


# --------------------------------------------------------------------------- finding 1: USD


def _usda(tmp_path: Path, body: str) -> Path:
    folder = tmp_path / "asset"
    folder.mkdir(exist_ok=True)
    path = folder / "c.usda"
    path.write_text("#usda 1.0\n" + body)
    return path


def test_usd_sublayer_outside_the_folder_is_refused(tmp_path):
    (tmp_path / "secret.usda").write_text('#usda 1.0\ndef Xform "Secret" {}\n')
    for ref in ("../secret.usda", str(tmp_path / "secret.usda")):
        path = _usda(tmp_path, f"(\n    subLayers = [@{ref}@]\n)\n")
        with pytest.raises(InputError, match="leads outside the file's folder") as exc:
            load_character(path)
        assert str(tmp_path) not in str(exc.value) and "secret" not in str(exc.value)
        opened, result = _opened_while_reading(path, tmp_path)
        assert "leads outside" in result
        assert os.path.realpath(tmp_path / "secret.usda") not in opened


def test_usd_reference_inside_the_folder_reads(tmp_path):
    path = _usda(tmp_path, 'def Xform "Root" (\n    references = @inner.usda@\n)\n{\n}\n')
    (path.parent / "inner.usda").write_text('#usda 1.0\n(\n    defaultPrim = "X"\n)\ndef Xform "X" {}\n')
    assert load_character(path).skeleton.names == ()


@pytest.mark.parametrize("kind", ["dev_zero", "fifo"])
def test_usd_input_must_be_a_regular_file(kind, tmp_path):
    path = tmp_path / "c.usda"
    os.symlink("/dev/zero", path) if kind == "dev_zero" else os.mkfifo(path)
    out = _run_inspect(path, tmp_path)
    assert out.returncode == 2 and "not a regular file" in out.stderr, out.stderr


# --------------------------------------------------------------------------- finding 10: out of spec


def _glb(tmp_path: Path, mutate=None, data_edit=None, name="c.glb") -> Path:
    """tiny_skinned as a GLB, after ``mutate(gl)`` and ``data_edit(gl, bytearray)``."""
    gl, data = tiny_skinned()
    data = bytearray(data)
    if mutate is not None:
        mutate(gl)
    if data_edit is not None:
        data_edit(gl, data)
    path = tmp_path / name
    path.write_bytes(glb_bytes(gl, bytes(data)))
    return path


def _put(gl: dict, data: bytearray, accessor: int, values, dtype=np.float32) -> None:
    """Overwrite the start of an accessor's bytes."""
    a = gl["accessors"][accessor]
    raw = np.asarray(values, dtype=dtype).tobytes()
    off = gl["bufferViews"][a["bufferView"]].get("byteOffset", 0) + a.get("byteOffset", 0)
    data[off:off + len(raw)] = raw


def _attr(gl, key):
    return gl["meshes"][0]["primitives"][0]["attributes"][key]


def _ctype(key, ctype, normalized=False, quantization=False):
    def mutate(gl):
        gl["accessors"][_attr(gl, key)]["componentType"] = ctype
        if normalized:
            gl["accessors"][_attr(gl, key)]["normalized"] = True
        if quantization:
            gl["extensionsUsed"] = gl["extensionsRequired"] = ["KHR_mesh_quantization"]
    return mutate


@pytest.mark.parametrize("key, ctype, match", [
    ("POSITION", 5125, "POSITION is stored as UNSIGNED_INT"),
    ("POSITION", 5122, "POSITION is stored as SHORT without KHR_mesh_quantization"),
    ("WEIGHTS_0", 5125, "WEIGHTS_0 is stored as UNSIGNED_INT"),
    ("WEIGHTS_0", 5120, "WEIGHTS_0 is stored as BYTE"),
])
def test_attribute_types_outside_the_spec_are_refused(key, ctype, match, tmp_path):
    with pytest.raises(InputError, match=f"mesh 'Body': {match}, which glTF 2.0 does not allow"):
        read_gltf(_glb(tmp_path, _ctype(key, ctype)))


def test_quantized_positions_read_with_the_extension(tmp_path):
    c = read_gltf(_glb(tmp_path, _ctype("POSITION", 5122, quantization=True)))
    assert len(c.meshes[0].positions) == 4
    with pytest.raises(InputError, match="POSITION is stored as UNSIGNED_INT"):  # never allowed
        read_gltf(_glb(tmp_path, _ctype("POSITION", 5125, quantization=True), name="d.glb"))


def test_normalized_weights_are_allowed(tmp_path):
    def weights(gl, data):
        gl["accessors"][_attr(gl, "WEIGHTS_0")].update(componentType=5121, normalized=True)
        _put(gl, data, _attr(gl, "WEIGHTS_0"), np.tile([255, 0, 0, 0], 4), np.uint8)

    c = read_gltf(_glb(tmp_path, data_edit=weights))
    assert np.allclose(c.meshes[0].weights.sum(axis=1), 1.0) and c.warnings == ()


def test_position_outside_its_declared_bounds_is_reported(tmp_path):
    """A flipped POSITION value outside the accessor's min/max: the Khronos validator's
    ACCESSOR_ELEMENT_OUT_OF_MIN_BOUND, accepted silently before; now a repair warning (the
    writer recomputes the bounds). Valid bounds give no warning."""
    assert read_gltf(_glb(tmp_path)).warnings == ()

    def out_of_bounds(gl):
        acc = gl["accessors"][_attr(gl, "POSITION")]
        acc["min"] = [m + 1.0 for m in acc["min"]]

    c = read_gltf(_glb(tmp_path, out_of_bounds, name="b.glb"))
    assert any("POSITION" in w and "declared min/max differ from the data" in w for w in c.warnings), c.warnings


def test_zero_rest_rotation_is_repaired_with_a_warning(tmp_path):
    c = read_gltf(_glb(tmp_path, lambda gl: gl["nodes"][1].update(rotation=[0, 0, 0, 0])))
    assert np.allclose(c.skeleton.rotations[1], [0, 0, 0, 1])
    assert any("nodes[1] 'j1': rest rotation quaternion is zero: replaced by the identity" in w for w in c.warnings)


def test_zero_key_rotation_is_repaired_with_a_warning(tmp_path):
    def zero_key(gl, data):
        _put(gl, data, gl["animations"][0]["samplers"][0]["output"], [0, 0, 0, 0])

    c = read_gltf(_glb(tmp_path, data_edit=zero_key))
    assert np.allclose(c.clips[0].tracks[0].values[0], [0, 0, 0, 1])
    assert any("1 zero rotation quaternions replaced by the identity" in w for w in c.warnings)


def test_overflowing_quaternion_is_normalized_safely(tmp_path):
    """[1e300, 0, 0, 1e300] has an infinite norm: it used to become the identity, silently."""
    c = read_gltf(_glb(tmp_path, lambda gl: gl["nodes"][1].update(rotation=[1e300, 0, 0, 1e300])))
    r = c.skeleton.rotations[1]
    assert np.all(np.isfinite(r)) and np.allclose(np.abs(r), [0.5 ** 0.5, 0, 0, 0.5 ** 0.5])
    assert any("rest rotation quaternion is not unit: normalized" in w for w in c.warnings)


def test_huge_key_rotation_is_normalized_with_a_warning(tmp_path):
    def huge(gl, data):
        _put(gl, data, gl["animations"][0]["samplers"][0]["output"], [3e38, 0, 0, 3e38])

    c = read_gltf(_glb(tmp_path, data_edit=huge))
    assert np.allclose(c.clips[0].tracks[0].values[0], [0.5 ** 0.5, 0, 0, 0.5 ** 0.5])
    assert any("1 rotation quaternions not unit: normalized" in w for w in c.warnings)


def test_negative_key_times_are_refused(tmp_path):
    def negative(gl, data):
        t = gl["animations"][0]["samplers"][0]["input"]
        _put(gl, data, t, [-1.0, 1.0])
        gl["accessors"][t]["min"] = [-1.0]

    with pytest.raises(InputError, match=r"key time -1\.0 is negative"):
        read_gltf(_glb(tmp_path, data_edit=negative))


@pytest.mark.parametrize("ctype, name", [(5121, "UNSIGNED_BYTE"), (5123, "UNSIGNED_SHORT")])
def test_integer_key_times_are_refused(ctype, name, tmp_path):
    """Key times must be FLOAT; UNSIGNED_BYTE times were read as whole seconds (a warning about
    their order only)."""
    def integer_times(gl):
        gl["accessors"][gl["animations"][0]["samplers"][0]["input"]]["componentType"] = ctype

    with pytest.raises(InputError, match=f"input \\(key times\\) is stored as {name}, which glTF 2.0 does not allow"):
        read_gltf(_glb(tmp_path, integer_times))


def test_scene_node_out_of_range_is_refused(tmp_path):
    with pytest.raises(InputError, match=r"scenes\[0\]\.nodes refers to nodes\[999\], which does not exist"):
        read_gltf(_glb(tmp_path, lambda gl: gl["scenes"][0].update(nodes=[999])))
    with pytest.raises(InputError, match=r"scenes\[0\]\.nodes lists nodes\[1\], a child of nodes\[0\]"):
        read_gltf(_glb(tmp_path, lambda gl: gl["scenes"][0].update(nodes=[0, 1]), name="d.glb"))
    with pytest.raises(InputError, match=r"scenes\[3\] does not exist"):
        read_gltf(_glb(tmp_path, lambda gl: gl.update(scene=3), name="e.glb"))


@pytest.mark.parametrize("ext", ["EXT_unknown_thing", "KHR_texture_transform", "KHR_materials_variants"])
def test_unknown_required_extension_is_refused(ext, tmp_path):
    def require(gl):
        gl["extensionsUsed"] = gl["extensionsRequired"] = [ext]

    with pytest.raises(UnsupportedError, match=f"requires extension '{ext}', which rigmix cannot read"):
        read_gltf(_glb(tmp_path, require))


def test_known_extension_used_but_not_required_reads(tmp_path):
    c = read_gltf(_glb(tmp_path, lambda gl: gl.update(extensionsUsed=["KHR_texture_transform"])))
    assert c.skeleton.names == ("j0", "j1", "j2")


def _ibm(values):
    def edit(gl, data):
        ibm = gl["accessors"][gl["skins"][0]["inverseBindMatrices"]]
        off = gl["bufferViews"][ibm["bufferView"]].get("byteOffset", 0) + 64  # joint 1
        data[off:off + 64] = np.asarray(values, np.float32).reshape(16).tobytes()
    return edit


@pytest.mark.parametrize("values, match", [
    (np.where(np.eye(4) > 0, np.nan, 0.0).T, "holds NaN or infinite values"),
    (np.where(np.eye(4) > 0, np.inf, 0.0).T, "holds NaN or infinite values"),
    (np.zeros((4, 4)), "is not affine"),
    (np.diag([1.0, 0.0, 1.0, 1.0]).T, "is not invertible"),
    (np.array([[1, 0, 0, 0], [2, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], float), "is not invertible"),
])
def test_bad_inverse_bind_matrix_is_refused_naming_it(values, match, tmp_path, capsys):
    path = _glb(tmp_path, data_edit=_ibm(values))
    with pytest.raises(InputError, match=rf"skins\[0\] inverseBindMatrices\[1\] \(joint 'j1'\) {match}"):
        read_gltf(path)
    assert cli_main(["inspect", str(path)]) == 2
    assert "inverseBindMatrices[1] (joint 'j1')" in capsys.readouterr().err


def test_small_but_valid_inverse_bind_scale_reads(tmp_path):
    """A centimetre skin (scale 0.01 in the inverse binds) is not singular."""
    c = read_gltf(_glb(tmp_path, data_edit=_ibm(np.diag([0.01, 0.01, 0.01, 1.0]))))
    assert np.allclose(c.skeleton.inverse_binds[1], np.diag([0.01, 0.01, 0.01, 1.0]))


# Out-of-spec files with one reading: read, each defect named in a warning (make fuzz counted
# them as "silently accepted": exit 0, no warning, Khronos validator errors).
OUT_OF_SPEC = {
    "json-edit-RiggedFigure-del-primitives": "has no primitives",
    "json-edit-RiggedFigure-del-channel-target": "has no target",
    "json-edit-RiggedFigure-node-name-int": "not a string",
    "json-edit-RiggedFigure-node-matrix-and-trs": "both a matrix and",
    "nan-inf-Fox-node-matrix-zero": "matrix is singular",
    "nan-inf-Fox-position-huge": "declares no min/max",
    "anim-time-RiggedFigure-anim-times-1e30": "declares no min/max",
    "scene-RiggedFigure-scene-nodes-empty": "nodes is empty",
}


@pytest.mark.parametrize("case_id", sorted(OUT_OF_SPEC))
def test_out_of_spec_file_is_read_with_a_warning(case_id, tmp_path):
    import hostile
    from conftest import asset

    case = next(c for c in hostile.all_cases() if c.id == case_id)
    asset(hostile.SEEDS[hostile.seed_of(case)][0])
    path = hostile.Workspace(tmp_path).materialize(case)
    errors, _ = hostile.validator_report(path, case.special)
    assert errors, f"{case_id}: the Khronos validator accepts it; the case tests nothing"
    warnings = load_character(path).warnings
    assert any(OUT_OF_SPEC[case_id] in w for w in warnings), warnings
