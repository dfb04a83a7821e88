"""Shared fixtures: the real characters in ../shared/data/characters (or $RIGMIX_ASSETS) and the
corpus in ../shared/data/corpus (or $RIGMIX_CORPUS).

With CI=true a missing asset is a failure, not a skip.

``composed`` (session): a composition config composed once per test run, for the tests that
check the same composition; they carry the ``xdist_group`` mark :data:`COMPOSED_GROUP`, so that
``make test`` (``--dist loadgroup``) runs them in one worker process and the cache serves them all.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
ASSETS = Path(os.environ.get("RIGMIX_ASSETS", ROOT.parent / "shared" / "data" / "characters"))
CORPUS = Path(os.environ.get("RIGMIX_CORPUS", ROOT.parent / "shared" / "data" / "corpus"))

#: name -> path relative to CORPUS, the 19 corpus characters (../shared/data/corpus/README.md)
CORPUS_CHARACTERS = {
    "Adventurer": "Adventurer/Adventurer.glb",
    "Apatosaurus": "Apatosaurus/Apatosaurus.glb",
    "Bee": "Bee/Bee.glb",
    "Bull": "Bull/Bull.glb",
    "Crab": "Crab/Crab.glb",
    "CyberpunkCharacter": "CyberpunkCharacter/Character.glb",
    "Deer": "Deer/Deer.glb",
    "EnemyLarge": "EnemyLarge/Enemy_Large.glb",
    "EnemyTwoLegs": "EnemyTwoLegs/Enemy_2Legs.glb",
    "Frog": "Frog/Frog.glb",
    "Leela": "Leela/Leela.glb",
    "PlatformerCharacter": "PlatformerCharacter/Character.glb",
    "Rat": "Rat/Rat.glb",
    "Snake": "Snake/Snake.glb",
    "Stegosaurus": "Stegosaurus/Stegosaurus.glb",
    "Trex": "Trex/Trex.glb",
    "Triceratops": "Triceratops/Triceratops.glb",
    "Witch": "Witch/Witch.glb",
    "Wolf": "Wolf/Wolf.glb",
}

#: name -> path relative to ASSETS, every shared character.
CHARACTERS = {
    "CesiumMan": "CesiumMan/CesiumMan.glb",
    "RiggedFigure": "RiggedFigure/RiggedFigure.glb",
    "Knight": "QuaterniusKnight/KnightCharacter.glb",
    "Fox": "Fox/Fox.glb",
    "Horse": "QuaterniusHorse/Horse.glb",
    "Wasp": "QuaterniusWasp/Wasp.glb",
    "Velociraptor": "QuaterniusVelociraptor/Velociraptor.glb",
    "SimpleSkin": "SimpleSkin/SimpleSkin.gltf",
}


#: ``pytest.mark.xdist_group`` name of the tests that share :func:`composed`'s compositions
COMPOSED_GROUP = "composed"
#: mark for such a test (``pytestmark = IN_COMPOSED_GROUP`` for a whole module)
IN_COMPOSED_GROUP = pytest.mark.xdist_group(COMPOSED_GROUP)


def require(what: str, ok: bool) -> None:
    """Skip (or, under CI=true, fail) when a test dependency such as Chromium or EGL is missing."""
    if ok:
        return
    msg = f"missing {what}"
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(msg)
    pytest.skip(msg)


def asset(name: str) -> Path:
    """Path of a shared character; fails under CI=true, skips elsewhere, when it is missing."""
    path = ASSETS / CHARACTERS.get(name, name)
    require(f"test asset {path} (set RIGMIX_ASSETS to the characters folder)", path.exists())
    return path


def corpus(name: str) -> Path:
    """Path of a corpus character; fails under CI=true, skips elsewhere, when it is missing."""
    path = CORPUS / CORPUS_CHARACTERS.get(name, name)
    require(f"corpus character {path} (set RIGMIX_CORPUS to the corpus folder)", path.exists())
    return path


def corpus_case(name: str, tmp_path) -> Path:
    """The corpus matrix's config ``name`` (``kind__Character__...``), written under ``tmp_path``;
    fails under CI=true, skips elsewhere, when one of its characters is missing."""
    from benchmarks.corpus_matrix import GENERATORS, load_subjects, write_configs

    characters = [p for p in name.split("__")[1:] if p in CHARACTERS or p in CORPUS_CHARACTERS]
    for c in characters:
        asset(c) if c in CHARACTERS else corpus(c)
    case = next(c for c in GENERATORS[name.split("__")[0]](load_subjects(characters)) if c.name == name)
    return write_configs([case], tmp_path)[name]


def fused_twice(config, **changes):
    """``config`` composed up to its fusion, and its fusion inputs fused again with ``changes`` to
    its fusion parameters (``crossing_rounds=0``: the same fusion with a stage turned off).

    Returns
    -------
    inputs : list of FusionInput
    surface : FusedSurface
        The composition's own.
    changed : FusedSurface
        With the changed parameters.
    """
    from dataclasses import replace

    from rigmix.fusion import fuse_surfaces
    from rigmix.fusion.inputs import fusion_inputs_from_plan
    from rigmix.pipeline import compose

    comp = compose(config, until="fusion")
    inputs, actions, _ = fusion_inputs_from_plan(comp.plan)
    changed = fuse_surfaces(inputs, actions, params=replace(comp.config.fusion.to_params(), **changes))
    return inputs, comp.surface, changed


def with_fusion(config, **changes):
    """``config`` (a :class:`rigmix.config.Config` or its file) with ``changes`` to its ``[fusion]``
    section."""
    from rigmix.config import Config, load_config

    config = config if isinstance(config, Config) else load_config(Path(config))
    return config.model_copy(update={"fusion": config.fusion.model_copy(update=changes)})


def tail_config(scale: float = 0.65, extra: str = "", name: str = "tail") -> str:
    """A composition config ``name``: the built-in humanoid with the quadruped's tail attached,
    nearest junction weights (a few seconds); ``extra`` is TOML inserted before the actions."""
    return f"""name = "{name}"
[characters.human]
path = "builtin:humanoid"
[characters.animal]
path = "builtin:quadruped"
scale = {scale}
{extra}
[[actions]]
op = "attach"
source = "animal"
source_joint = "Tail.1"
target = "human"
target_joint = "Hips"
[weights]
method = "nearest"
"""


@pytest.fixture(params=sorted(CHARACTERS))
def character_path(request) -> Path:
    """Each shared character in turn."""
    return asset(request.param)


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch thread for a module: two xdist workers share two cores, and one thread each
    trains a DFD field faster than two."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def composed():
    """``composed(config_path)``: :func:`rigmix.compose` of a TOML config, every stage, made once per
    test run (each xdist worker) and shared: keyed by the file's bytes and folder (relative character
    paths resolve from it). A :class:`rigmix.pipeline.Composition` is immutable (stages return new
    ones), so a test may ``dataclasses.replace`` it or run stages on it, never change its arrays in
    place. The full composition serves a test that needs fewer stages: each stage only adds fields.
    """
    from rigmix.pipeline import compose

    cache = {}

    def get(path):
        path = Path(path).resolve()
        key = (hashlib.sha256(path.read_bytes()).hexdigest(), str(path.parent))
        if key not in cache:
            cache[key] = compose(path)
        return cache[key]

    return get
