"""``compose(config)``: the stages of the method in order, nothing else.

Reads like the paper's overview (PIPELINE.md):

1. load the input characters (files or ``builtin:`` examples), mirrored where the config says;
2. operations: output skeleton S_R with provenance, scale matching, preliminary positioning
   (:func:`rigmix.operations.plan_operations`);
3. bone-to-bone mappings B_i with confidence (:func:`rigmix.mapping.map_bones`);
4. surface fusion M_R (:func:`rigmix.fusion.fuse_surfaces`);
5. skinning weights W_R (:func:`rigmix.weights.blend.blend_weights`);
6. animation completion A_R (:func:`rigmix.animation.completion.complete_clips`);
7. assembly of the output character (:func:`rigmix.assemble.assemble_character`);
8. quality figures (:func:`rigmix.quality.junction_stretch_ratio`,
   :func:`rigmix.quality.junction_weight_roughness`).

Each stage is one explicit call in :func:`compose`. The stage adapters (``*_stage``) all live
here: each takes a :class:`Composition`, reads its options from the config's typed section
(checked at load, :mod:`rigmix.config`), and returns ``dataclasses.replace(composition, ...)``
with its results (typed fields and entries of ``report``); none mutates its input.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from .character import Character, Clip, Skeleton
from .errors import InputError
from .geometry import check_coordinates

if TYPE_CHECKING:  # the annotations of Composition; the stages import their packages on use
    from .config import Config
    from .fusion import FusedSurface, FusionInput
    from .operations import Plan
    from .weights import SkinWeights

__all__ = ["Composition", "Progress", "Step", "STAGE_NAMES", "check_input", "load_characters", "compose",
           "mapping_table", "fusion_stage", "weights_stage", "completion_stage", "assembly_stage", "quality_stage",
           "builtin_character", "keep_builtin"]

logger = logging.getLogger(__name__)

#: ``progress(stage, done, total)``: called as each stage starts (``stage`` the running one, ``done``
#: the number finished), as each sub-step of the fusion and the weights starts (``stage`` is then
#: ``"fusion: junction 1 of 2"``: the running stage, a colon and the sub-step; ``done`` unchanged)
#: and once at the end (``"done"``, ``total``, ``total``); the CLI turns it into a bar labelled
#: with the running stage and sub-step.
Progress = Callable[[str, int, int], None]

#: ``step(name)``: a stage function reports the sub-step it starts (see :data:`Progress`).
Step = Callable[[str], None]


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
    fusion_inputs : tuple of rigmix.fusion.FusionInput
        The positioned inputs given to the fusion, one per (character, mesh) part.
    fusion_ids : tuple of str
        The character id of each fusion input.
    surface : rigmix.fusion.FusedSurface or None
        M_R, after the fusion stage.
    weights : rigmix.weights.SkinWeights or None
        W_R, after the weights stage.
    clips : tuple of Clip or None
        A_R, after the completion stage.
    character : Character or None
        The composed character, after the assembly stage.
    report : dict
        JSON-ready figures: scales, fused pairs, timings per stage, ...
    """

    skeleton: Skeleton
    plan: Plan
    maps: dict
    inputs: dict
    config: Config
    fusion_inputs: tuple[FusionInput, ...] = ()
    fusion_ids: tuple[str, ...] = ()
    surface: FusedSurface | None = None
    weights: SkinWeights | None = None
    clips: tuple[Clip, ...] | None = None
    character: Character | None = None
    report: dict = field(default_factory=dict)


#: The stages :func:`compose` runs, in order (``until=`` takes one of these names).
STAGE_NAMES = ("load", "operations", "mapping", "fusion", "weights", "completion", "assembly", "quality")


def fusion_stage(composition: Composition, step: Step | None = None) -> Composition:
    """M_R: the fused rest surface (options: the config's ``[fusion]`` section).

    Returns the composition with ``fusion_inputs``, ``fusion_ids``,
    ``surface`` (:class:`rigmix.fusion.FusedSurface`) and ``report["mesh"]`` (the fusion's figures,
    then the rest-pose figures of :func:`rigmix.quality.grafted_visibility` and
    :func:`rigmix.quality.junction_dihedral`, and ``replaced_whole_region``), ``report["fields"]``.

    Where a fusion gate fails (:func:`rigmix.gates.mesh_gates`), the surface may be fused a second
    time with the replaced regions taken whole (``FusionParams.retry_whole_region``), and that one
    kept when it fails less (:func:`rigmix.gates.fails_less`); the stage's time then holds both,
    and ``report["mesh"]["rejected_attempt"]`` holds the fusion not kept: its ``mesh`` and
    ``fields`` figures and its ``failed_gates`` (names).
    """
    from .fusion import fuse_surfaces
    from .fusion.inputs import fusion_inputs_from_plan
    from .gates import failed_mesh_gates, fails_less
    from .quality import grafted_visibility, junction_dihedral

    plan = composition.plan
    inputs, actions, ids = fusion_inputs_from_plan(plan)
    roles = {cid: info["role"] for cid, info in plan.report["characters"].items()}
    params = composition.config.fusion.to_params()

    def fuse(params):
        surface = fuse_surfaces(inputs, actions, params=params, step=step)
        fused = replace(composition, fusion_inputs=tuple(inputs), fusion_ids=tuple(ids), surface=surface)
        mesh = {**surface.report["mesh"], **grafted_visibility(surface, inputs, ids, roles), **junction_dihedral(fused)}
        return fused, mesh

    fused, mesh = fuse(params)
    mesh["replaced_whole_region"] = not params.replaced_present
    failed = failed_mesh_gates(mesh)
    if (params.retry_whole_region and params.replaced_present and failed
            and any(x.replaced is not None and x.replaced.any() for x in inputs)
            and sum(len(x.F) for x in inputs) <= params.retry_max_faces):
        # the target's skin of a replaced joint, kept, can cover the new part (a stump in front of
        # it) or leave the junction too little room between the seams
        alt, alt_mesh = fuse(replace(params, replaced_present=False))
        alt_failed = failed_mesh_gates(alt_mesh)
        logger.info("fusion: failing %s; with the replaced regions taken whole, failing %s", sorted(failed),
                    sorted(alt_failed) or "no gate")
        alt_mesh = {**alt_mesh, "replaced_whole_region": True}
        attempts = [(fused, mesh, failed), (alt, alt_mesh, alt_failed)]
        if fails_less(alt_failed, failed):
            attempts.reverse()
        (fused, mesh, _), (rejected, rejected_mesh, rejected_failed) = attempts
        mesh = {**mesh, "rejected_attempt": {"mesh": rejected_mesh, "fields": rejected.surface.report["fields"],
                                             "failed_gates": sorted(rejected_failed)}}
    return replace(fused, report={**composition.report, "mesh": mesh, "fields": fused.surface.report["fields"]})


def weights_stage(composition: Composition, step: Step | None = None) -> Composition:
    """W_R on the fused surface (options: the config's ``[weights]`` section).

    Returns the composition with ``weights`` (:class:`rigmix.weights.SkinWeights`)
    and ``report["weights"]``.
    """
    from .weights import blend_weights

    maps = [composition.maps[cid] for cid in composition.fusion_ids]
    check_coordinates({"fused surface": composition.surface.V}, where=f"weights: config {composition.config.source}",
                      fix="the fusion produced vertices out of range; check the characters' placement and scale")
    skin = blend_weights(composition.surface, composition.fusion_inputs, maps, composition.skeleton.num_joints,
                         skeleton=composition.skeleton, params=composition.config.weights.to_params(), step=step)
    return replace(composition, weights=skin,
                   report={**composition.report, "weights": skin.report})


def completion_stage(composition: Composition, step: Step | None = None) -> Composition:
    """A_R: the clips of S_R (options: the config's ``[animation]`` section).

    Completes the clips of the inputs as loaded (rest-relative deltas carry them onto S_R,
    whatever scale and rest pose the positioning chose; translation keys go through
    :func:`rigmix.animation.completion.translation_maps`, into S_R's unit-scale frames), with the
    plan's provenance less the replaced limb roots whose rest bones disagree
    (:func:`rigmix.animation.completion.completion_provenance`).

    Returns the composition with ``clips`` (tuple of Clip on S_R) and ``report["animation"]``:
    ``sources`` (the ``[character id, clip name]`` each output clip of ``clips`` completes) and,
    per input, ``fidelity_max`` (:func:`rigmix.animation.fidelity.clip_fidelity`: the largest
    distance between a joint it keeps in the output clips and in its own clips, over the output's
    bounding-box diagonal), where it is (``fidelity_worst``) and the joints its clips drive by a
    confidence blend, not measured (``fidelity_blended_joints``).
    """
    from .animation.completion import complete_clips, completion_provenance, selected_clips, translation_maps
    from .animation.detached import detached_followers
    from .animation.fidelity import clip_fidelity
    from .geometry import bounding_box_diagonal

    options = composition.config.animation.to_params()
    plan = composition.plan
    sources = selected_clips(composition.inputs, options)
    provenance = completion_provenance(plan, options.rest_mismatch)
    clips = complete_clips(plan.skeleton, composition.inputs, composition.maps, selection=sources,
                           options=options, provenance=provenance,
                           translations=translation_maps(plan, composition.maps, composition.inputs),
                           followers=detached_followers(plan.skeleton, composition.inputs, composition.maps,
                                                        plan.provenance, plan.transforms))
    fidelity = clip_fidelity(plan.skeleton, clips, sources, composition.inputs, plan.positioned, plan.transforms,
                             provenance, composition.maps,
                             diagonal=bounding_box_diagonal(composition.surface.V if composition.surface is not None
                                                            else plan.skeleton.rest_worlds()[:, :3, 3]))
    report = {"clips": [c.name for c in clips], "sources": [list(k) for k in sources], "fps": options.fps,
              "frames": [int(len(c.tracks[0].times)) if c.tracks else 0 for c in clips],
              "jump_penalty": options.jump_penalty, "metric": options.metric,
              "fidelity_max": {cid: f.max for cid, f in fidelity.items()},
              "fidelity_worst": {cid: {"clip": f.clip, "joint": f.joint, "frame": f.frame}
                                 for cid, f in fidelity.items() if f.clip is not None},
              "fidelity_blended_joints": {cid: f.blended_joints for cid, f in fidelity.items()}}
    return replace(composition, clips=tuple(clips),
                   report={**composition.report, "animation": report})


def assembly_stage(composition: Composition, step: Step | None = None) -> Composition:
    """The output :class:`Character`: meshes by (input, material), weights, clips, props."""
    from .assemble import assemble_character

    character = assemble_character(composition)
    warnings = [w for ch in composition.inputs.values() for w in ch.warnings]
    return replace(composition, character=character, report={**composition.report, "warnings": warnings})


def quality_stage(composition: Composition, step: Step | None = None) -> Composition:
    """Figures that need no ground truth: the junction stretch ratio under animation and the
    junction weight roughness (weight spikes)."""
    from .quality import junction_stretch_ratio, junction_weight_roughness

    q = {**junction_stretch_ratio(composition), **junction_weight_roughness(composition)}
    return replace(composition, report={**composition.report, "quality": q})


#: name -> built-in character built (or received, :func:`keep_builtin`) in this process
_BUILTINS: dict[str, Character] = {}


def builtin_character(name: str) -> Character:
    """The built-in example character ``name`` (a function of :mod:`rigmix.examples`, e.g.
    ``"humanoid"``), built once per process: building one takes seconds.

    Raises
    ------
    KeyError
        Not a built-in character; its message lists the known names.
    """
    if name not in _BUILTINS:
        from . import examples  # imported on use

        fn = getattr(examples, name, None)
        if name.startswith("_") or not callable(fn) or name not in getattr(examples, "__all__", ()):
            known = [n for n in getattr(examples, "__all__", ()) if n.islower() and callable(getattr(examples, n))]
            raise KeyError(", ".join(known))
        _BUILTINS[name] = fn()
    return _BUILTINS[name]


def keep_builtin(name: str, character: Character) -> None:
    """Use ``character`` as the built-in ``name`` in this process from now on: one that another
    process built with :func:`builtin_character` (:mod:`rigmix.batch` shares them between its
    workers). Building is deterministic, so the composition is the same."""
    _BUILTINS[name] = character


def check_input(character: Character, *, fps: float | None = None) -> None:
    """Refuse what compose refuses in an input file before composing anything, with a line naming
    the file and the object: a stored rest pose that cannot be posed
    (:func:`rigmix.skinning.check_rig`) and clips too long to sample at ``fps``
    (:func:`rigmix.animation.sampling.check_clips`).

    Applied to the file as stored (moving its rest pose to the bind pose would hide a singular
    one); ``rigmix inspect`` applies it at the default fps, so it refuses what compose refuses.

    Parameters
    ----------
    character : Character
        As read from its file.
    fps : float, optional
        The completion rate (``[animation] fps``); default :class:`rigmix.animation.CompletionOptions`'.

    Raises
    ------
    InputError
    """
    from .animation.completion import CompletionOptions
    from .animation.sampling import check_clips
    from .skinning import check_rig

    check_rig(character)
    check_clips(character, CompletionOptions.fps if fps is None else fps)


@lru_cache(maxsize=16)
def _load_file(path: str, mtime: float, pose: str = "bind", fps: float | None = None) -> Character:
    from .io import load_character
    from .skinning import rest_at_bind

    character = load_character(path)
    check_input(character, fps=fps)
    if pose == "rest":
        return character
    # composed in the pose its mesh is bound in: animations stay exact (rest_at_bind)
    return rest_at_bind(character)


def load_characters(config: Config) -> dict:
    """Load every character of a config (a file read twice under two ids is read once).

    Returns
    -------
    dict of str -> Character
        By character id, in the config's order, each file's rest pose moved to its bind pose
        where they differ (:func:`rigmix.skinning.rest_at_bind`; not with ``[positioning] pose =
        "rest"``); a character with ``mirror`` set
        in the config is mirrored (:func:`rigmix.operations.mirror.mirror_character`, joint sides
        swapped).

    Raises
    ------
    InputError
        A missing file, an unknown ``builtin:`` name, a file the reader rejects or that cannot be
        composed (:func:`check_input`, at the config's ``[animation] fps``).
    """
    from .config import BUILTIN_PREFIX, check_files

    check_files(config)
    out = {}
    for cid in config.characters:
        p = config.character_path(cid)
        if isinstance(p, str):
            name = p[len(BUILTIN_PREFIX):]
            try:
                out[cid] = builtin_character(name)
            except KeyError as e:
                raise InputError(f"config {config.source}: characters.{cid}.path: no built-in character "
                                 f"{name!r}; known: {e.args[0]}") from None
        else:
            out[cid] = _load_file(str(p.resolve()), p.stat().st_mtime, config.positioning.pose, config.animation.fps)
        mirror = config.characters[cid].mirror
        if mirror is not False:  # before everything else: actions name the mirrored joints
            from .operations.mirror import mirror_character

            out[cid] = mirror_character(out[cid], axis=None if mirror is True else mirror)
    return out


def compose(config, *, progress: Progress | None = None, until: str | None = None) -> Composition:
    """Compose a new character from pieces of the input characters.

    Parameters
    ----------
    config : Config, str or Path
        A config built in code, or a TOML file (read with :func:`rigmix.config.load_config`).
    progress : callable, optional
        ``progress(stage, done, total)`` as each stage and sub-step starts, then
        ``("done", total, total)`` (:data:`Progress`).
    until : str, optional
        Stop after this stage (one of :data:`STAGE_NAMES`), e.g. ``until="mapping"`` for
        ``rigmix map``.

    Returns
    -------
    Composition

    Raises
    ------
    rigmix.errors.RigmixError
        InputError for a bad config or input file, UnsupportedError for an input without a
        skin, NumericalError from a numerical stage.
    """
    from .config import Config, load_config
    from .mapping import map_bones
    from .operations import plan_operations

    if not isinstance(config, Config):
        config = load_config(Path(config))
    if until is not None and until not in STAGE_NAMES[2:]:  # a Composition starts with the mapping
        raise ValueError(f"compose: unknown stage {until!r}; stages: {', '.join(STAGE_NAMES[2:])}")
    clock = _StageClock(progress, STAGE_NAMES.index(until) if until is not None else len(STAGE_NAMES) - 1)

    inputs = clock.run("load", load_characters, config)
    plan = clock.run("operations", plan_operations, inputs, config)  # S_R, provenance, positioning
    maps = clock.run("mapping", map_bones, plan, score=config.mapping.score,
                     injectivity_bonus=config.mapping.injectivity_bonus)  # B_i with confidence
    report = {"name": config.name, "config": config.source, "operations": plan.report,
              "scales": {cid: float(s) for cid, s in plan.scales.items()},
              "timings": {}}  # filled in on return
    comp = Composition(plan.skeleton, plan, maps, inputs, config, report=report)
    comp = clock.stage("fusion", fusion_stage, comp)            # M_R
    comp = clock.stage("weights", weights_stage, comp)          # W_R
    comp = clock.stage("completion", completion_stage, comp)    # A_R
    comp = clock.stage("assembly", assembly_stage, comp)        # the output character
    comp = clock.stage("quality", quality_stage, comp)          # junction stretch under animation
    return replace(comp, report={**comp.report, "timings": clock.timings()})


class _StageClock:
    """Times the stages of one :func:`compose` call, reports them to ``progress`` and skips
    the stages after the last one asked for (``last``, an index of :data:`STAGE_NAMES`)."""

    def __init__(self, progress: Progress | None, last: int):
        self._progress = progress
        self._last = last
        self._seconds = {}
        self._start = time.perf_counter()

    def run(self, name: str, fn: Callable, *args, **kwargs):
        """``fn(*args, **kwargs)``, timed as stage ``name``."""
        index = STAGE_NAMES.index(name)
        if self._progress is not None:
            self._progress(name, index, self._last + 1)
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        self._seconds[name] = round(time.perf_counter() - t0, 4)
        if self._progress is not None and index == self._last:
            self._progress("done", self._last + 1, self._last + 1)
        return out

    def stage(self, name: str, fn: Callable[[Composition, Step | None], Composition],
              composition: Composition) -> Composition:
        """``fn(composition, step)`` timed as stage ``name``, its sub-steps reported as
        ``"name: step"``; ``composition`` itself when ``name`` comes after the last stage asked for."""
        index = STAGE_NAMES.index(name)
        if index > self._last:
            return composition
        step = None
        if self._progress is not None:
            def step(sub: str, progress=self._progress, total=self._last + 1) -> None:
                progress(f"{name}: {sub}", index, total)
        return self.run(name, fn, composition, step)

    def timings(self) -> dict:
        """Seconds per stage run, in order, and ``total`` since the clock started."""
        return {**self._seconds, "total": round(time.perf_counter() - self._start, 4)}


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
