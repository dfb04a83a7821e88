"""Property-based fuzzing: only RigmixError may escape the reader and the config validation.

Mutations of real small files (SimpleSkin written as GLB by ``write_gltf``, RiggedFigure, and the
synthetic skinned GLB of ``test_bad_inputs``): byte flips, truncations, chunk-length changes and
JSON field mutations (each field replaced by a value of another type or range, or deleted).
A file that still reads must also write. Configs: dicts built from the schema's keys with values
of every type, and mutations of the shipped example configs.

Fixed budget, deterministic (``derandomize=True``, no example database): 640 cases.
"""

from __future__ import annotations

import json
import math
import struct
import tempfile
import tomllib
from pathlib import Path

import pytest
from conftest import ROOT, asset
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from test_bad_inputs import glb_bytes, tiny_skinned

from rigmix.config import parse_config
from rigmix.errors import InputError, RigmixError
from rigmix.io.gltf import read_gltf, write_gltf

FUZZ = settings(derandomize=True, deadline=None, database=None, print_blob=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.filter_too_much])

# --------------------------------------------------------------------------- seed files

_SEEDS: dict[str, bytes] = {}
_WORK = tempfile.TemporaryDirectory(prefix="rigmix-fuzz-")


def seeds() -> dict[str, bytes]:
    """name -> GLB bytes of the seed files (built once per process)."""
    if not _SEEDS:
        gl, data = tiny_skinned()
        _SEEDS["synthetic"] = glb_bytes(gl, data)
        simple = Path(_WORK.name) / "SimpleSkin.glb"
        write_gltf(read_gltf(asset("SimpleSkin")), simple)
        _SEEDS["SimpleSkin"] = simple.read_bytes()
        _SEEDS["RiggedFigure"] = asset("RiggedFigure").read_bytes()
    return _SEEDS


def split_glb(raw: bytes) -> tuple[dict, bytes]:
    """A valid GLB's JSON (dict) and BIN chunk."""
    n = struct.unpack_from("<I", raw, 12)[0]
    js = json.loads(raw[20:20 + n])
    return js, raw[28 + n:]


def check_reads_or_refuses(raw: bytes, name: str = "fuzz.glb") -> None:
    """Read ``raw``: a Character or a RigmixError; a Character must also write."""
    path = Path(_WORK.name) / name
    path.write_bytes(raw)
    try:
        character = read_gltf(path)
    except RigmixError as exc:
        assert str(exc) and "\n" not in str(exc)
        event(f"refused: {type(exc).__name__}")
        return
    try:
        write_gltf(character, Path(_WORK.name) / "out.glb")
        event("read and written")
    except RigmixError as exc:
        event(f"read, write refused: {type(exc).__name__}")


# --------------------------------------------------------------------------- GLB bytes

SEED_NAMES = ["synthetic", "SimpleSkin", "RiggedFigure"]


@pytest.fixture(scope="module", autouse=True)
def _seeds_present():
    seeds()


@settings(FUZZ, max_examples=160)
@given(seed=st.sampled_from(SEED_NAMES), flips=st.lists(st.tuples(st.floats(0, 1, exclude_max=True),
                                                                  st.integers(1, 255)), min_size=1, max_size=8))
def test_byte_flips(seed, flips):
    raw = bytearray(seeds()[seed])
    for where, mask in flips:
        raw[int(where * len(raw))] ^= mask
    check_reads_or_refuses(bytes(raw))


@settings(FUZZ, max_examples=60)
@given(seed=st.sampled_from(SEED_NAMES), where=st.floats(0, 1, exclude_max=True))
def test_truncations(seed, where):
    raw = seeds()[seed]
    check_reads_or_refuses(raw[: int(where * len(raw))])


@settings(FUZZ, max_examples=60)
@given(seed=st.sampled_from(SEED_NAMES), field=st.sampled_from(["length", "json", "bin"]),
       value=st.one_of(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 3, 2**31, 2**32 - 1])),
       )
def test_header_and_chunk_lengths(seed, field, value):
    raw = bytearray(seeds()[seed])
    n = struct.unpack_from("<I", raw, 12)[0]
    offset = {"length": 8, "json": 12, "bin": 20 + n}[field]
    struct.pack_into("<I", raw, offset, value)
    check_reads_or_refuses(bytes(raw))


def _paths(obj, prefix=()):
    """Every (key or index) path in a JSON value, containers included."""
    out = [prefix] if prefix else []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj[:64]):  # long arrays: their head is enough
            out += _paths(v, prefix + (i,))
    return out


_PATHS: dict[str, list] = {}


def json_paths(seed: str) -> list:
    if seed not in _PATHS:
        _PATHS[seed] = _paths(split_glb(seeds()[seed])[0])
    return _PATHS[seed]


#: Replacement values: other types, other ranges, the JSON extensions NaN and Infinity.
WEIRD = st.one_of(
    st.sampled_from([None, True, False, 0, -1, 1, 2, 3, 255, 65535, 2**31, 2**32, 2**53, 2**64, -(2**63),
                     0.5, -0.0, 1e308, math.nan, math.inf, -math.inf, "", "x", "LINEAR", "VEC4", "MAT4",
                     [], [0], [math.nan] * 3, [0, 0, 0, 0], [1e30] * 16, {}, {"bufferView": 0}]),
    st.integers(-(2**40), 2**40),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.lists(st.integers(-5, 70000), max_size=5),
)


@settings(FUZZ, max_examples=200)
@given(seed=st.sampled_from(SEED_NAMES), data=st.data())
def test_json_field_mutations(seed, data):
    js, bin_chunk = split_glb(seeds()[seed])
    paths = json_paths(seed)
    for _ in range(data.draw(st.integers(1, 3), label="mutations")):
        path = paths[data.draw(st.integers(0, len(paths) - 1), label="path")]
        parent = js
        try:
            for k in path[:-1]:
                parent = parent[k]
            if data.draw(st.booleans(), label="delete") and isinstance(parent, dict):
                parent.pop(path[-1], None)
            else:
                parent[path[-1]] = data.draw(WEIRD, label="value")
        except (KeyError, IndexError, TypeError):
            continue  # an earlier mutation removed or replaced this path
    check_reads_or_refuses(glb_bytes(json.dumps(js).encode(), bin_chunk))


# --------------------------------------------------------------------------- configs

NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(10**6), 10**6))
ANY = st.recursive(
    st.one_of(st.none(), st.booleans(), NUMBERS, st.text(max_size=10)),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=4)),
    max_leaves=10,
)
JOINT = st.one_of(st.sampled_from(["Hips", "Spine", "UpperArm.L", "Neck", "Tail.1", ""]), ANY)
CHARACTER = st.fixed_dictionaries({"path": st.one_of(st.sampled_from(["builtin:humanoid", "builtin:nope", "x.glb",
                                                                      "${NOPE_VAR}/a.glb", ""]), ANY)},
                                  optional={
                                      "scale": st.one_of(st.just("auto"), NUMBERS, ANY),
                                      "rotations": st.dictionaries(JOINT.filter(lambda j: isinstance(j, str)),
                                                                   st.one_of(st.lists(NUMBERS, max_size=5), ANY),
                                                                   max_size=2),
                                      "placement": st.one_of(st.fixed_dictionaries(
                                          {}, optional={"translation": st.lists(NUMBERS, max_size=4),
                                                        "rotation": st.lists(NUMBERS, max_size=5)}), ANY),
                                      "extra": ANY,
                                  })
IDS = st.sampled_from(["a", "b", "c"])
ACTION = st.fixed_dictionaries(
    {"op": st.one_of(st.sampled_from(["attach", "replace", "remove", "graft"]), ANY)},
    optional={"source": st.one_of(IDS, ANY), "target": st.one_of(IDS, ANY), "source_joint": JOINT,
              "target_joint": JOINT, "mode": st.one_of(st.sampled_from(["blend", "union", "mix"]), ANY)})
CONFIG = st.fixed_dictionaries(
    {},
    optional={
        "name": st.one_of(st.text(max_size=8), ANY),
        "characters": st.one_of(st.dictionaries(IDS, CHARACTER, max_size=3), ANY),
        "actions": st.one_of(st.lists(ACTION, max_size=3), ANY),
        "mapping": st.one_of(st.fixed_dictionaries({}, optional={
            "score": st.sampled_from(["paper", "prototype", "best"]),
            "injectivity_bonus": st.lists(NUMBERS, max_size=3)}), ANY),
        "positioning": ANY,
        "fusion": ANY,
        "weights": ANY,
        "unknown": ANY,
    })


def check_config(data) -> None:
    """``parse_config`` gives a Config (whose paths then resolve or raise InputError) or InputError."""
    try:
        cfg = parse_config(data, base_dir=ROOT, source="fuzz.toml")
    except InputError as exc:
        assert "fuzz.toml" in str(exc) and "\n" not in str(exc)
        return
    for cid in cfg.characters:
        try:
            cfg.character_path(cid)
        except InputError:
            pass


@settings(FUZZ, max_examples=100)
@given(data=CONFIG)
def test_config_dicts(data):
    check_config(data)


_EXAMPLES = {p.name: tomllib.loads(p.read_text()) for p in sorted((ROOT / "examples").glob("*.toml"))}


@settings(FUZZ, max_examples=60)
@given(name=st.sampled_from(sorted(_EXAMPLES)), data=st.data())
def test_example_config_mutations(name, data):
    cfg = json.loads(json.dumps(_EXAMPLES[name]))
    paths = _paths(cfg)
    path = paths[data.draw(st.integers(0, len(paths) - 1), label="path")]
    parent = cfg
    for k in path[:-1]:
        parent = parent[k]
    if data.draw(st.booleans(), label="delete") and isinstance(parent, dict):
        del parent[path[-1]]
    else:
        parent[path[-1]] = data.draw(st.one_of(WEIRD, ANY), label="value")
    check_config(cfg)
