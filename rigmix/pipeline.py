"""``compose(config)``: the stages of the method in order, nothing else.

Reads like the paper's overview (PIPELINE.md):

1. load the input characters (files or ``builtin:`` examples);
2. operations: output skeleton S_R with provenance, scale matching, preliminary positioning
   (:func:`rigmix.operations.plan_operations`);
3. bone-to-bone mappings B_i with confidence (:func:`rigmix.mapping.map_bones`);
4. surface fusion M_R, 5. skinning weights W_R, 6. animation completion A_R: stages added to
   :data:`STAGES` by their modules (each takes and returns a :class:`Composition`).

Later stages register with :func:`register_stage` (or are appended to :data:`STAGES`) and
return ``dataclasses.replace(composition, ...)`` with their results (``character`` and entries
of ``report``); they never mutate their input.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Callable

from .character import Character, Skeleton
from .config import BUILTIN_PREFIX, Config, check_files, load_config
from .errors import InputError
from .mapping import map_bones
from .operations import Plan, plan_operations

__all__ = ["Composition", "Progress", "STAGES", "register_stage", "load_characters", "compose", "mapping_table"]

logger = logging.getLogger(__name__)

#: ``progress(stage, done, total)``: called as stages finish; the CLI turns it into a bar.
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class Composition:
    """The result of :func:`compose`, stage by stage.

    Attributes
    ----------
    skeleton : Skeleton
        S_R, the output skeleton.
    plan : rigmix.operations.Plan
        Provenance, used joints, fused pairs, the positioned inputs and their scales.
    maps : dict of str -> BoneMap
        B_i per input character id.
    inputs : dict of str -> Character
        The characters as loaded.
    config : Config
    character : Character or None
        The composed character, once the fusion, weight and animation stages have run.
    stages : dict
        Results of later stages by name (e.g. ``"surface"``, ``"weights"``, ``"clips"``).
    report : dict
        JSON-ready figures: scales, fused pairs, timings per stage, ...
    """

    skeleton: Skeleton
    plan: Plan
    maps: dict
    inputs: dict
    config: Config
    character: Character | None = None
    stages: dict = field(default_factory=dict)
    report: dict = field(default_factory=dict)


#: Stages after the mapping, in order: ``(name, function(Composition, progress) -> Composition)``.
STAGES: list[tuple[str, Callable]] = []


def register_stage(name: str, fn: Callable, *, before: str | None = None) -> None:
    """Add (or replace) a stage run by :func:`compose` after the mapping.

    Parameters
    ----------
    name : str
        E.g. ``"fusion"``, ``"weights"``, ``"animation"``.
    fn : callable
        ``fn(composition, progress) -> Composition``.
    before : str, optional
        Insert before this stage instead of at the end.
    """
    for i, (n, _) in enumerate(STAGES):
        if n == name:
            STAGES[i] = (name, fn)
            return
    if before is not None:
        for i, (n, _) in enumerate(STAGES):
            if n == before:
                STAGES.insert(i, (name, fn))
                return
    STAGES.append((name, fn))


@lru_cache(maxsize=8)
def _builtin(name: str) -> Character:
    from . import examples  # imported on use: building an example takes seconds

    fn = getattr(examples, name, None)
    if name.startswith("_") or not callable(fn) or name not in getattr(examples, "__all__", ()):
        known = [n for n in getattr(examples, "__all__", ()) if n.islower() and callable(getattr(examples, n))]
        raise KeyError(", ".join(known))
    return fn()


@lru_cache(maxsize=16)
def _load_file(path: str, mtime: float) -> Character:
    from .io import load_character

    return load_character(path)


def load_characters(config: Config) -> dict:
    """Load every character of a config (a file read twice under two ids is read once).

    Returns
    -------
    dict of str -> Character
        By character id, in the config's order.

    Raises
    ------
    InputError
        A missing file, an unknown ``builtin:`` name, or a file the reader rejects.
    """
    check_files(config)
    out = {}
    for cid in config.characters:
        p = config.character_path(cid)
        if isinstance(p, str):
            name = p[len(BUILTIN_PREFIX):]
            try:
                out[cid] = _builtin(name)
            except KeyError as e:
                raise InputError(f"config {config.source}: characters.{cid}.path: no built-in character "
                                 f"{name!r}; known: {e.args[0]}") from None
        else:
            out[cid] = _load_file(str(p.resolve()), p.stat().st_mtime)
    return out


def compose(config, *, progress: Progress | None = None, until: str | None = None) -> Composition:
    """Compose a new character from pieces of the input characters.

    Parameters
    ----------
    config : Config, str or Path
        A config built in code, or a TOML file (read with :func:`rigmix.config.load_config`).
    progress : callable, optional
        ``progress(stage, done, total)`` after each stage.
    until : str, optional
        Stop after this stage (``"mapping"`` or a registered stage's name),
        e.g. ``until="mapping"`` for ``rigmix map``.

    Returns
    -------
    Composition

    Raises
    ------
    rigmix.errors.RigmixError
        InputError for a bad config or input file, UnsupportedError for an input without a
        skin, NumericalError from a numerical stage.
    """
    if not isinstance(config, Config):
        config = load_config(Path(config))
    names = ["mapping"] + [n for n, _ in STAGES]
    if until is not None and until not in names:
        raise ValueError(f"compose: unknown stage {until!r}; stages: {', '.join(names)}")
    stages = list(STAGES) if until is None else list(STAGES)[: names.index(until)]
    total = 3 + len(stages)
    timings = {}

    def done(stage, k, t0):
        timings[stage] = round(time.perf_counter() - t0, 4)
        if progress is not None:
            progress(stage, k, total)

    t0 = time.perf_counter()
    inputs = load_characters(config)
    done("load", 1, t0)

    t0 = time.perf_counter()
    plan = plan_operations(inputs, config)  # S_R, provenance, positioning
    done("operations", 2, t0)

    t0 = time.perf_counter()
    maps = map_bones(plan, score=config.mapping.score,
                     injectivity_bonus=config.mapping.injectivity_bonus)  # B_i with confidence
    done("mapping", 3, t0)

    report = {"name": config.name, "config": config.source, "operations": plan.report, "timings": timings}
    comp = Composition(plan.skeleton, plan, maps, inputs, config, report=report)
    # fusion (M_R), weights (W_R), animation (A_R): registered by their modules
    for k, (name, fn) in enumerate(list(stages), start=4):
        t0 = time.perf_counter()
        comp = fn(comp, progress)
        done(name, k, t0)
    return replace(comp, report={**comp.report, "timings": timings})


def mapping_table(composition: Composition) -> list[dict]:
    """Rows ``{character, input_joint, output_joint, confidence}`` of every B_i (for the CLI)."""
    rows = []
    names_out = composition.skeleton.names
    for cid, bm in composition.maps.items():
        names_in = composition.inputs[cid].skeleton.names
        for j, (t, c) in enumerate(zip(bm.target, bm.confidence)):
            rows.append({"character": cid, "input_joint": names_in[j],
                         "output_joint": names_out[t] if t >= 0 else None, "confidence": float(c)})
    return rows
