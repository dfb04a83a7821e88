"""The composition config: TOML schema, paths, errors that name the file and the key."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import asset

from rigmix.config import (
    Config,
    ReplaceAction,
    config_schema,
    default_assets_dir,
    expand_path,
    load_config,
    parse_config,
)
from rigmix.errors import InputError

CONFIGS = Path(__file__).parent / "configs"
EXAMPLES = Path(__file__).parent.parent / "examples"


def write(tmp_path, text, name="c.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_paths_relative_to_config_file(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "a.glb").write_bytes(b"")
    p = write(tmp_path, '[characters.a]\npath = "sub/a.glb"\n')
    cfg = load_config(p)
    assert cfg.character_path("a") == tmp_path / "sub" / "a.glb"
    assert cfg.source == str(p)
    assert cfg.base_dir == tmp_path


def test_rigmix_assets_expansion(tmp_path, monkeypatch):
    monkeypatch.setenv("RIGMIX_ASSETS", str(tmp_path))
    (tmp_path / "x.glb").write_bytes(b"")
    cfg = parse_config({"characters": {"a": {"path": "${RIGMIX_ASSETS}/x.glb"}}}, base_dir="/elsewhere")
    assert cfg.character_path("a") == tmp_path / "x.glb"
    monkeypatch.delenv("RIGMIX_ASSETS")
    # default: ../shared/data/characters beside the repository
    repo = Path(__file__).resolve().parent.parent
    assert default_assets_dir() == repo.parent / "shared" / "data" / "characters"
    assert expand_path("${RIGMIX_ASSETS}/x.glb", "/tmp") == repo.parent / "shared" / "data" / "characters" / "x.glb"


def test_rigmix_corpus_expansion(tmp_path, monkeypatch):
    monkeypatch.setenv("RIGMIX_CORPUS", str(tmp_path))
    assert expand_path("${RIGMIX_CORPUS}/Bee/Bee.glb", "/elsewhere") == tmp_path / "Bee" / "Bee.glb"
    monkeypatch.delenv("RIGMIX_CORPUS")
    # default: ../shared/data/corpus beside the repository, like RIGMIX_ASSETS
    repo = Path(__file__).resolve().parent.parent
    assert expand_path("${RIGMIX_CORPUS}/x.glb", "/tmp") == repo.parent / "shared" / "data" / "corpus" / "x.glb"


def test_unset_variable_is_an_input_error(monkeypatch):
    monkeypatch.delenv("RIGMIX_NO_SUCH_VAR", raising=False)
    cfg = parse_config({"characters": {"a": {"path": "${RIGMIX_NO_SUCH_VAR}/x.glb"}}})
    with pytest.raises(InputError, match="RIGMIX_NO_SUCH_VAR"):
        cfg.character_path("a")


def test_builtin_paths_are_kept():
    cfg = parse_config({"characters": {"a": {"path": "builtin:humanoid"}}})
    assert cfg.character_path("a") == "builtin:humanoid"


def test_full_config_parses(tmp_path):
    (tmp_path / "h.glb").write_bytes(b"")
    (tmp_path / "k.glb").write_bytes(b"")
    p = write(tmp_path, """
name = "centaur"
[characters.horse]
path = "h.glb"
[characters.knight]
path = "k.glb"
scale = 0.5
placement = { translation = [1, 2, 3], rotation = [0, 90, 0] }
[characters.knight.rotations]
"UpperArm.L" = [0, 0, -30]
"UpperArm.R" = { quaternion = [0, 0, 0.2588190451, 0.9659258263] }
"Neck" = { euler = [10, 0, 0], order = "zyx" }
[[actions]]
op = "replace"
source = "knight"
source_joint = "Abdomen"
target = "horse"
target_joint = "Neck1"
mode = "union"
[[actions]]
op = "attach"
source = "knight"
source_joint = "Head"
target = "horse"
target_joint = "Tail1"
[[actions]]
op = "remove"
target = "horse"
target_joint = "Ear1.L"
[mapping]
score = "prototype"
""")
    cfg = load_config(p)
    assert cfg.name == "centaur"
    k = cfg.characters["knight"]
    assert k.scale == 0.5
    assert cfg.characters["horse"].scale == "auto"
    assert [a.op for a in cfg.actions] == ["replace", "attach", "remove"]
    assert isinstance(cfg.actions[0], ReplaceAction) and cfg.actions[0].mode == "union"
    q = k.rotations["UpperArm.L"].as_quaternion()
    assert q == pytest.approx([0, 0, -0.258819045, 0.965925826], abs=1e-8)
    assert k.rotations["UpperArm.R"].as_quaternion() == pytest.approx([0, 0, 0.258819045, 0.965925826], abs=1e-8)
    assert k.placement.translation == (1, 2, 3)
    assert cfg.mapping.score == "prototype"


def test_config_built_in_code_equals_loaded(tmp_path):
    (tmp_path / "a.glb").write_bytes(b"")
    p = write(tmp_path, '[characters.a]\npath = "a.glb"\n'
                        '[[actions]]\nop = "remove"\ntarget = "a"\ntarget_joint = "j"\n')
    loaded = load_config(p)
    built = Config(characters={"a": {"path": "a.glb"}}, actions=[{"op": "remove", "target": "a", "target_joint": "j"}])
    assert built.model_dump() == loaded.model_dump()
    assert built.with_base_dir(tmp_path).character_path("a") == loaded.character_path("a")


@pytest.mark.parametrize("text, key", [
    ('[characters.a]\npath = "x"\nscal = 1\n', "characters.a.scal: unknown key"),
    ('[characters.a]\npath = "x"\n[[actions]]\nop = "remove"\ntarget = "a"\ntarget_joint = "j"\nmode = "blend"\n',
     "actions[0].mode: unknown key"),
    ('[characters.a]\npath = "x"\nscale = -1\n', "characters.a.scale"),
    ('[characters.a]\npath = "x"\n[characters.a.rotations]\nj = [1, 2]\n', "characters.a.rotations.j"),
    ('[characters.a]\npath = "x"\n[[actions]]\nop = "graft"\ntarget = "a"\ntarget_joint = "j"\n', "actions[0]"),
    ('[characters.a]\npath = "x"\n[[actions]]\nop = "attach"\ntarget = "a"\ntarget_joint = "j"\n',
     "actions[0].source"),
    ('characters = {}\n', "characters"),
    ('[characters.a]\npath = "x"\n[mapping]\nscore = "best"\n', "mapping.score"),
])
def test_invalid_configs_name_file_and_key(tmp_path, text, key):
    p = write(tmp_path, text, "bad.toml")
    with pytest.raises(InputError) as e:
        load_config(p)
    msg = str(e.value)
    assert "bad.toml" in msg and key in msg
    assert "\n" not in msg  # one line for the CLI


def test_unknown_character_lists_closest(tmp_path):
    p = write(tmp_path, '[characters.horse]\npath = "x"\n[[actions]]\nop = "remove"\ntarget = "hrose"\n'
                        'target_joint = "j"\n', "bad.toml")
    with pytest.raises(InputError, match=r"actions\[0\]\.target: unknown character 'hrose'.*closest: horse"):
        load_config(p)


def test_missing_files(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load_config(tmp_path / "nope.toml")
    p = write(tmp_path, '[characters.a]\npath = "missing.glb"\n', "m.toml")
    with pytest.raises(InputError, match=r"m\.toml: characters\.a\.path: no such file .*missing\.glb"):
        load_config(p)


def test_not_toml(tmp_path):
    p = write(tmp_path, "[characters.a\npath=", "broken.toml")
    with pytest.raises(InputError, match="broken.toml: not valid TOML"):
        load_config(p)


def test_schema_is_json_and_strict():
    s = config_schema()
    json.dumps(s)
    assert set(s["properties"]) >= {"characters", "actions", "mapping", "name"}
    assert s["additionalProperties"] is False
    defs = s["$defs"]
    assert {"AttachAction", "ReplaceAction", "RemoveAction", "CharacterConfig"} <= set(defs)
    assert all(d.get("additionalProperties") is False for d in defs.values() if d.get("type") == "object")


def test_shipped_configs_parse():
    """Every example and test config is valid (paths resolved, files checked when present)."""
    files = sorted(CONFIGS.glob("*.toml")) + sorted(EXAMPLES.glob("*.toml"))
    assert len(files) >= 6
    for f in files:
        if "${RIGMIX_ASSETS}" in f.read_text():
            asset("Horse")  # skip without the shared characters; fail under CI
        cfg = load_config(f)
        assert cfg.characters


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def test_cli_schema(capsys):
    from rigmix.cli import main

    assert main(["schema"]) == 0
    out = capsys.readouterr().out
    assert json.loads(out) == config_schema()


@pytest.mark.parametrize("name, words", [
    ("unknown_joint", ["target_joint", "'Nek1'", "closest: Neck1"]),
    ("unknown_key", ["characters.knight.scal", "unknown key"]),
    ("cycle", ["cycle"]),
    ("self_attach", ["grafted onto itself"]),
    ("missing_file", ["characters.horse.path", "no such file", "NoSuchHorse.glb"]),
])
def test_cli_bad_configs_fail_with_one_line_and_no_output(capsys, name, words):
    from rigmix.cli import main

    path = CONFIGS / "bad" / f"{name}.toml"
    if name != "missing_file":
        asset("Horse")  # the bad configs name real characters: fail under CI if they are missing
    assert main(["map", str(path)]) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    err = [line for line in cap.err.splitlines() if line.startswith("rigmix: error:")]
    assert len(err) == 1 and f"{name}.toml" in err[0]
    for w in words:
        assert w in err[0]


def test_error_naming_an_odd_key_stays_on_one_line():
    # found by the fuzz test: a key holding a newline broke the one-line error contract
    with pytest.raises(InputError) as info:
        parse_config({"characters": {"\n": None}}, source="odd.toml")
    message = str(info.value)
    assert "odd.toml" in message and "\n" not in message and '"\\n"' in message


# --------------------------------------------------------------------------------------------
# The stage sections: [fusion], [weights], [animation], [gates]
# --------------------------------------------------------------------------------------------

SECTIONS = [("fusion", "FusionParams", "FUSION_RANGES"), ("weights", "WeightParams", "WEIGHT_RANGES"),
            ("animation", "CompletionOptions", "ANIMATION_RANGES"), ("gates", "GateBounds", "GATE_RANGES")]


def _params_class(name):
    import rigmix.animation
    import rigmix.fusion
    import rigmix.gates
    import rigmix.weights

    return {"FusionParams": rigmix.fusion.FusionParams, "WeightParams": rigmix.weights.WeightParams,
            "CompletionOptions": rigmix.animation.CompletionOptions, "GateBounds": rigmix.gates.GateBounds}[name]


@pytest.mark.parametrize("section, params, ranges", SECTIONS)
def test_every_stage_option_has_a_range_entry(section, params, ranges):
    import dataclasses

    import rigmix.config

    names = [f.name for f in dataclasses.fields(_params_class(params))]
    assert sorted(getattr(rigmix.config, ranges)) == sorted(names)


@pytest.mark.parametrize("section, params, ranges", SECTIONS)
def test_absent_section_gives_the_dataclass_defaults(section, params, ranges):
    cfg = parse_config({"characters": {"a": {"path": "x"}}})
    assert getattr(cfg, section).to_params() == _params_class(params)()


@pytest.mark.parametrize("text, words", [
    ("[weights]\nsmothing = 30\n", ["weights.smothing: unknown key", "closest: smoothing"]),
    ("[fusion]\nvoxel_factr = 1.0\n", ["fusion.voxel_factr: unknown key", "closest: voxel_factor"]),
    ("[animation]\njump_penalt = 0.1\n", ["animation.jump_penalt: unknown key", "closest: jump_penalty"]),
    ('[animation]\nfixed_frames = [{character = "a", clip = "c", frame = 0, source = "a", source_clip = "c", '
     'source_fram = 0}]\n', ["animation.fixed_frames[0].source_fram: unknown key", "closest: source_frame"]),
    ('[weights]\nsmoothing = "30"\n', ["weights.smoothing", "valid integer"]),
    ("[weights]\nmax_influences = 2.5\n", ["weights.max_influences", "valid integer"]),
    ("[fusion]\nkeep_input_corners = 1\n", ["fusion.keep_input_corners", "valid boolean"]),
    ("[fusion]\nsmooth_iterations = true\n", ["fusion.smooth_iterations", "valid integer"]),
    ('[animation]\nfps = "30"\n', ["animation.fps", "valid number"]),
    ('[animation]\nclips = { a = "walk" }\n', ["animation.clips.a"]),
    ("[weights]\nmin_confidence = 1.5\n", ["weights.min_confidence", "less than or equal to 1"]),
    ("[weights]\nmax_influences = 0\n", ["weights.max_influences", "greater than or equal to 1"]),
    ("[fusion]\nvoxel_factor = 0\n", ["fusion.voxel_factor", "greater than 0"]),
    ("[fusion]\nsmooth_iterations = -1\n", ["fusion.smooth_iterations", "greater than or equal to 0"]),
    ("[fusion]\nfidelity_relax = [4.0, -1]\n", ["fusion.fidelity_relax[1]", "greater than 0"]),
    ('[fusion]\nbackend = "vdb"\n', ["fusion.backend", "'openvdb'"]),
    ("[fusion]\nmargin_voxels = nan\n", ["fusion.margin_voxels", "finite number"]),
    ("[animation]\nfps = 0\n", ["animation.fps", "greater than or equal to 1"]),
    ("[animation]\nfps = 1e-9\n", ["animation.fps", "greater than or equal to 1"]),
    ("[fusion]\nband_voxels = 1e9\n", ["fusion.band_voxels", "less than or equal to 4096"]),
    ('[positioning]\ntranslate = "yes"\n', ["positioning.translate", "valid boolean"]),
    ("[animation]\nrest_mismatch = 181\n", ["animation.rest_mismatch", "less than or equal to 180"]),
    ("[animation]\nhops_full = 4\nhops_max = 3\n", ["animation", "hops_max must be >= hops_full"]),
    ("[gates]\nmax_seconds = 0\n", ["gates.max_seconds", "greater than 0"]),
    ('[gates]\nmax_seconds = "60"\n', ["gates.max_seconds", "valid number"]),
    ("[gates]\nmax_second = 60\n", ["gates.max_second: unknown key", "closest: max_seconds"]),
])
def test_invalid_stage_options_fail_at_load(tmp_path, text, words):
    (tmp_path / "a.glb").write_bytes(b"")
    p = write(tmp_path, '[characters.a]\npath = "a.glb"\n' + text, "bad.toml")
    with pytest.raises(InputError) as e:
        load_config(p)
    msg = str(e.value)
    assert "bad.toml" in msg and "\n" not in msg
    for w in words:
        assert w in msg


def test_stage_options_reach_the_dataclasses(tmp_path):
    from rigmix.animation.completion import FixedFrame

    (tmp_path / "a.glb").write_bytes(b"")
    p = write(tmp_path, """[characters.a]
path = "a.glb"
[fusion]
voxel_factor = 1
fidelity_relax = [2, 4.5]
[weights]
method = "inpaint"
smoothing = 30
[animation]
continuity = [0.3]
clips = { a = ["walk"] }
fixed_frames = [{character = "a", clip = "walk", frame = 0, source = "a", source_clip = "walk", source_frame = 2}]
""")
    cfg = load_config(p)
    fusion, weights, animation = cfg.fusion.to_params(), cfg.weights.to_params(), cfg.animation.to_params()
    assert fusion.voxel_factor == 1.0 and fusion.fidelity_relax == (2.0, 4.5)
    assert weights.method == "inpaint" and weights.smoothing == 30 and weights.max_influences == 4
    assert animation.continuity == (0.3,) and animation.clips == {"a": ["walk"]}
    assert animation.fixed_frames == (FixedFrame("a", "walk", 0, "a", "walk", 2),)


def test_with_options_overrides_and_checks(tmp_path):
    (tmp_path / "a.glb").write_bytes(b"")
    cfg = load_config(write(tmp_path, '[characters.a]\npath = "a.glb"\n[weights]\nsmoothing = 3\n'))
    out = cfg.with_options(weights={"method": "nearest"}, fusion={"keep_fields": True})
    assert out.weights.method == "nearest" and out.weights.smoothing == 3 and out.fusion.keep_fields
    assert out.source == cfg.source and out.base_dir == cfg.base_dir
    assert cfg.weights.method == "dfd"  # the original is unchanged
    with pytest.raises(InputError, match=r"c\.toml: weights\.smothing: unknown key \(closest: smoothing"):
        cfg.with_options(weights={"smothing": 1})


def test_schema_documents_every_stage_option():
    import dataclasses

    s = config_schema()
    for section, params, _ in SECTIONS:
        ref = s["properties"][section]["$ref"].rsplit("/", 1)[1]
        props = s["$defs"][ref]["properties"]
        names = [f.name for f in dataclasses.fields(_params_class(params))]
        assert sorted(props) == sorted(names), section
        missing = [n for n in names if not props[n].get("description")]
        assert not missing, (section, missing)


def test_cli_unknown_stage_option_exits_2(tmp_path, capsys):
    from rigmix.cli import main

    for section, key, closest in [("weights", "smothing", "smoothing"), ("fusion", "voxel_factr", "voxel_factor"),
                                  ("animation", "jump_penalt", "jump_penalty")]:
        p = write(tmp_path, f'[characters.a]\npath = "builtin:humanoid"\n[{section}]\n{key} = 30\n', "typo.toml")
        assert main(["compose", str(p), "-o", str(tmp_path / "out.glb"), "--no-progress"]) == 2
        err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("rigmix: error:")]
        assert len(err) == 1 and f"{section}.{key}: unknown key" in err[0] and f"closest: {closest}" in err[0]
        assert not (tmp_path / "out.glb").exists()


@pytest.mark.parametrize("section, key", [("fusion", "smooth_iterations"), ("fusion", "remesh_iterations"),
                                          ("weights", "smoothing"), ("animation", "blend_frames"),
                                          ("animation", "fps")])
def test_iterative_options_are_bounded(tmp_path, section, key):
    """``1e9`` iterations hung the fusion for minutes, ``fps = 1e9`` exhausted memory: every
    iterative option has an upper bound checked at load."""
    base = '[characters.a]\npath = "builtin:humanoid"\n'
    with pytest.raises(InputError, match=f"{section}.{key}"):
        load_config(write(tmp_path, base + f"[{section}]\n{key} = 1000000000\n"))


def test_deeply_nested_toml_is_an_input_error(tmp_path):
    """tomllib parses nested arrays recursively: 100,000 levels gave RecursionError (exit 1)."""
    with pytest.raises(InputError, match="nested too deep"):
        load_config(write(tmp_path, "x = " + "[" * 100_000 + "]" * 100_000 + "\n"))


@pytest.mark.parametrize("extra", ['scale = true', 'scale = "1"', 'placement = { translation = ["1", 0, 0] }',
                                   'placement = { rotation = [true, 0, 0] }'])
def test_numbers_are_not_coerced_from_bools_or_strings(tmp_path, extra):
    """``scale = true`` composed at scale 1 and a string translation was read as a number."""
    text = f'[characters.a]\npath = "builtin:humanoid"\n{extra}\n'
    with pytest.raises(InputError, match="characters.a"):
        load_config(write(tmp_path, text))
    load_config(write(tmp_path, '[characters.a]\npath = "builtin:humanoid"\nscale = 2\n', name="ok.toml"))
