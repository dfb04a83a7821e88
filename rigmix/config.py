"""The composition config: which characters, which actions (PIPELINE.md section 1).

A config is a TOML file validated by a strict pydantic schema (``extra="forbid"``: a typo is an
error naming the key), or a :class:`Config` built in code. ``rigmix schema`` prints
:func:`config_schema`.

.. code-block:: toml

    name = "centaur"                      # optional, the output character's name

    [characters.horse]
    path = "${RIGMIX_ASSETS}/QuaterniusHorse/Horse.glb"
    [characters.knight]
    path = "knight.glb"                   # relative to this config file
    scale = "auto"                        # or a number (the override)
    placement = { translation = [0, 0, 0], rotation = [0, 90, 0] }
    mirror = false                        # true, "x", "y" or "z": reflect it first (rigmix.operations.mirror)
    [characters.knight.rotations]         # rest-pose rotations, degrees (XYZ) or xyzw quaternion
    "UpperArm.L" = [0, 0, -30]
    "UpperArm.R" = { quaternion = [0, 0, 0.2588, 0.9659] }

    [[actions]]
    op = "replace"                        # attach | replace | remove
    source = "knight"
    source_joint = "Body"
    target = "horse"
    target_joint = "Neck1"
    mode = "blend"                        # replace only: blend | union
    keep_joint = false                    # attach only: source_joint stays its own joint, a child of target_joint

    [positioning]
    pose = "bind"                         # bind (animations exact) | rest (the files' stored rest pose)
    [fusion]                              # rigmix.fusion.FusionParams
    voxel_factor = 0.8
    [weights]                             # rigmix.weights.WeightParams
    method = "dfd"
    [animation]                           # rigmix.animation.CompletionOptions
    jump_penalty = 0.2
    [gates]                               # rigmix.gates.GateBounds
    max_seconds = 120

The ``[fusion]``, ``[weights]``, ``[animation]`` and ``[gates]`` sections are built from the
parameter dataclasses of their stages (:class:`FusionOptions`, :class:`WeightOptions`,
:class:`AnimationOptions`, :class:`GateOptions`): the same fields and defaults, with types and
ranges checked at load; ``to_params()`` gives the stage its dataclass.

Paths: relative paths are resolved against the config file's folder (or
:meth:`Config.with_base_dir`); ``${NAME}`` is replaced by the environment variable ``NAME``,
``${RIGMIX_ASSETS}`` defaults to ``../shared/data/characters`` beside the repository and
``${RIGMIX_CORPUS}`` to ``../shared/data/corpus`` (:data:`DATA_DIRS`).
``builtin:NAME`` names a procedural character of :mod:`rigmix.examples` (``builtin:humanoid``).
"""

from __future__ import annotations

import collections.abc
import dataclasses
import difflib
import inspect
import json
import math
import os
import re
import tomllib
import types
import typing
from pathlib import Path
from typing import Annotated, ClassVar, Literal, Union

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    Strict,
    StrictBool,
    ValidationError,
    create_model,
    field_validator,
    model_validator,
)

from .animation.completion import CompletionOptions
from .errors import InputError
from .fusion import FusionParams
from .gates import GateBounds
from .geometry import MAX_COORDINATE, MAX_GRID_VOXELS
from .weights.params import WeightParams

__all__ = [
    "JointRotation",
    "Placement",
    "CharacterConfig",
    "AttachAction",
    "ReplaceAction",
    "RemoveAction",
    "Action",
    "MappingOptions",
    "PositioningOptions",
    "FusionOptions",
    "WeightOptions",
    "AnimationOptions",
    "GateOptions",
    "FUSION_RANGES",
    "WEIGHT_RANGES",
    "ANIMATION_RANGES",
    "GATE_RANGES",
    "FUSION_TYPES",
    "Config",
    "load_config",
    "parse_config",
    "check_files",
    "config_schema",
    "expand_path",
    "closest_names",
    "default_assets_dir",
    "default_data_dir",
    "DATA_DIRS",
    "BUILTIN_PREFIX",
    "MIN_SCALE",
    "MAX_SCALE",
    "MAX_EULER_DEGREES",
    "MAX_QUATERNION_COMPONENT",
]

#: Prefix of a path that names a procedural character of :mod:`rigmix.examples`.
BUILTIN_PREFIX = "builtin:"

_STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # TOML has nan and inf

#: Bounds of a character's scale (an override, or the one chosen by ``"auto"``): four orders of
#: magnitude either way hold every unit conversion (millimetres, centimetres, inches to metres
#: and back: 1e-3 to 1e3) with a factor 10 to spare. Beyond them the two characters differ in
#: size by more than a fusion grid resolves (at most 250 voxels across), and a 1e9 scale
#: overflows the grid's voxel count.
MIN_SCALE, MAX_SCALE = 1e-4, 1e4

#: Largest Euler angle, in degrees: one turn either way expresses every rotation.
MAX_EULER_DEGREES = 360.0

#: Largest quaternion component (normalized on use): keeps the squared length finite.
MAX_QUATERNION_COMPONENT = 1e6

# strict: an int is a number, a bool or a string is not (TOML `true` or "1" would coerce)
_Degrees = Annotated[float, Strict(), Field(ge=-MAX_EULER_DEGREES, le=MAX_EULER_DEGREES)]
_QuaternionComponent = Annotated[float, Strict(), Field(ge=-MAX_QUATERNION_COMPONENT, le=MAX_QUATERNION_COMPONENT)]
_Coordinate = Annotated[float, Strict(), Field(ge=-MAX_COORDINATE, le=MAX_COORDINATE)]  # metres (rigmix.geometry)


class JointRotation(BaseModel):
    """A rotation, in degrees (Euler angles) or as a unit quaternion xyzw.

    In TOML, a list of 3 numbers is shorthand for ``{euler = [...]}`` and a list of 4 for
    ``{quaternion = [...]}``.
    """

    model_config = _STRICT

    euler: tuple[_Degrees, _Degrees, _Degrees] | None = Field(
        None, description="Euler angles in degrees (within +-360), applied in `order`.")
    order: str = Field(
        "XYZ", pattern=r"^([XYZ]{3}|[xyz]{3})$",
        description="scipy Euler order: upper case intrinsic (e.g. XYZ), lower case extrinsic.")
    quaternion: tuple[_QuaternionComponent, _QuaternionComponent, _QuaternionComponent,
                      _QuaternionComponent] | None = Field(
        None, description="Unit quaternion x, y, z, w (normalized on use; components within +-1e6).")

    @model_validator(mode="before")
    @classmethod
    def _shorthand(cls, data):
        if isinstance(data, (list, tuple)):
            if len(data) == 3:
                return {"euler": data}
            if len(data) == 4:
                return {"quaternion": data}
            raise ValueError("a rotation list has 3 Euler angles (degrees) or 4 quaternion values (xyzw)")
        return data

    @model_validator(mode="after")
    def _one_form(self):
        if (self.euler is None) == (self.quaternion is None):
            raise ValueError("give exactly one of `euler` (degrees) or `quaternion` (xyzw)")
        if self.quaternion is not None and sum(q * q for q in self.quaternion) < 1e-12:
            raise ValueError("quaternion has zero length")
        return self

    def as_quaternion(self):
        """The rotation as a unit quaternion ``(4,)`` xyzw."""
        import numpy as np
        from scipy.spatial.transform import Rotation

        if self.quaternion is not None:
            q = np.asarray(self.quaternion, dtype=np.float64)
            return q / np.linalg.norm(q)
        return Rotation.from_euler(self.order, self.euler, degrees=True).as_quat()


class Placement(BaseModel):
    """A rigid placement of a whole character in world space, applied after its scale."""

    model_config = _STRICT

    translation: tuple[_Coordinate, _Coordinate, _Coordinate] = Field(
        (0.0, 0.0, 0.0), description="World translation, in the output's units (after scaling), each "
                                     "component within +-1e6 (rigmix.geometry.MAX_COORDINATE).")
    rotation: JointRotation | None = Field(
        None, description="World rotation about the origin, applied before the translation.")


class CharacterConfig(BaseModel):
    """One input character."""

    model_config = _STRICT

    path: str = Field(
        description="glTF/GLB file, relative to the config file, `${VAR}` expanded "
                    "(RIGMIX_ASSETS defaults to ../shared/data/characters beside the repository, RIGMIX_CORPUS "
                    "to ../shared/data/corpus), "
                    "or `builtin:NAME` for a procedural character of rigmix.examples.")
    scale: Literal["auto"] | Annotated[float, Strict()] = Field(
        "auto", description="Uniform scale applied before composing: a number in [1e-4, 1e4] (override) "
                            "or 'auto' (matched to the character it is fused with; 1 for a body).")
    rotations: dict[str, JointRotation] = Field(
        default_factory=dict,
        description="Rest-pose rotations per joint name, about the joint, in world axes, applied "
                    "parents first; the subtree and the mesh follow.")
    placement: Placement | None = Field(
        None, description="Rigid placement of the whole character (a moved character is then "
                          "translated onto its target anyway; the rotation still counts).")
    mirror: StrictBool | Literal["x", "y", "z"] = Field(
        False, description="Mirror the character before composing (rigmix.operations.mirror): true reflects it "
                           "across its detected symmetry plane (the axis plane of the rest pose it is "
                           "most symmetric about; x when none is), 'x', 'y' or 'z' across that axis "
                           "plane through its centre of symmetry. Joint names swap sides (.L <-> .R, "
                           "Left <-> Right, ...): actions and rotations name the mirrored joints, so "
                           "the original right arm is the mirrored character's left arm.")

    @field_validator("scale")
    @classmethod
    def _scale_range(cls, value):
        if value != "auto" and not MIN_SCALE <= value <= MAX_SCALE:
            raise ValueError(f"the scale must be 'auto' or a number in [{MIN_SCALE:g}, {MAX_SCALE:g}], "
                             f"got {value:g}")
        return value


class _ActionBase(BaseModel):
    model_config = _STRICT

    target: str = Field(description="Character id (a key of [characters]) that receives the action.")
    target_joint: str = Field(description="Joint of `target`, named as in its file.")


class AttachAction(_ActionBase):
    """Graft the subtree at `source_joint` of `source` onto `target_joint` of `target`.

    The two joints are fused into one joint of the output; the target keeps its whole subtree
    (field operator: union). With ``keep_joint``, `source_joint` stays a joint of its own, a child
    of `target_joint`.
    """

    op: Literal["attach"]
    source: str = Field(description="Character id that gives the subtree.")
    source_joint: str = Field(description="Root of the grafted subtree, fused with `target_joint`.")
    keep_joint: StrictBool = Field(
        False, description="Keep `source_joint` as a joint of its own, a child of `target_joint`, with its bone and "
                           "its motion in its clips (a wing that is one joint flaps by that joint), instead of fusing "
                           "the two. Several kept joints of one source attached at one target joint keep their "
                           "spacing: the source moves so that their mean lands on the target joint.")


class ReplaceAction(_ActionBase):
    """The subtree at `source_joint` of `source` replaces the subtree at `target_joint`.

    The two joints are fused; the target's descendants of `target_joint` are dropped.
    """

    op: Literal["replace"]
    source: str = Field(description="Character id that gives the subtree.")
    source_joint: str = Field(description="Root of the new subtree, fused with `target_joint`.")
    mode: Literal["blend", "union"] = Field(
        "blend", description="Surface operator at the junction: presence-weighted blend or union (min).")


class RemoveAction(_ActionBase):
    """Drop the subtree at `target_joint` (the joint included) and its surface."""

    op: Literal["remove"]


Action = Annotated[Union[AttachAction, ReplaceAction, RemoveAction], Field(discriminator="op")]


class MappingOptions(BaseModel):
    """Bone-to-bone mapping options (PIPELINE.md section 2; see :mod:`rigmix.mapping`)."""

    model_config = _STRICT

    score: Literal["paper", "prototype"] = Field(
        "paper", description="Candidate score: the paper's (geometric, topological, parametric, "
                             "valence) or the public prototype's (path, topology, directions, children).")
    injectivity_bonus: tuple[float, float] = Field(
        (0.5, 0.1), description="Ranking bonus for a candidate not picked yet, and for one picked "
                                "only with confidence < 1.")


class PositioningOptions(BaseModel):
    """Preliminary positioning options (PIPELINE.md section 1; see :mod:`rigmix.operations`)."""

    model_config = _STRICT

    translate: StrictBool = Field(
        True, description="Move each source character so that its fused joints land on their targets.")
    face: StrictBool = Field(
        True, description="Turn each source character moved onto another about the vertical (+Y) axis so that it "
                          "faces the way its target faces (both found by rigmix.limbs.classify_limbs: a wasp "
                          "modelled facing +X gives its wings to a humanoid facing +Z); only where their mirror planes "
                          "are perpendicular, and not where its placement sets a rotation.")
    detached_with_limb: StrictBool = Field(
        True, description="Move a limb's detached part (an IK foot that carries the foot's skin from the armature "
                          "root, replaced with its leg) as the limb's root moves, and rest the fused joint where the "
                          "part's skin is, so the foot stays at the end of its leg; false brings it onto the target's "
                          "joint, as every other fused pair (the foot then hangs where the target's foot was).")
    pose: Literal["bind", "rest"] = Field(
        "bind", description="Pose each file is composed in (and the output's rest pose), where a file's rest "
                            "pose differs per joint from the pose its mesh is bound in (every Quaternius rig): "
                            "'bind' keeps every animation exact (the rest pose moves to the bind pose); 'rest' "
                            "keeps the stored rest pose and moves the mesh there by skinning, which changes "
                            "how it deforms (a few % of its size on such rigs).")


# -- the stage sections: pydantic models built from the stages' parameter dataclasses ----------
# Each dataclass field needs an entry: the bounds of its number(s) (pydantic ``Field``
# constraints, applied to the number of an optional or to each item of a tuple), ``{}`` for none.
# The field's type, default and description come from the dataclass.

#: Most iterations (or rounds, rings, frames) any iterative option may ask for: every stage's
#: work stays bounded (the defaults are 2 to 10), so a typo like ``1e9`` is an error, not a hang.
MAX_ITERATIONS = 1000
#: Most frames per second the animation stages resample at (clips are sampled at ``fps``).
MAX_FPS = 240.0

#: Bounds of the ``[fusion]`` options (:class:`rigmix.fusion.FusionParams`).
FUSION_RANGES: dict[str, dict] = {
    "snap": {"ge": 0, "le": 1},
    "smooth_iterations": {"ge": 0, "le": MAX_ITERATIONS},
    "smooth_alpha": {"ge": 0, "le": 1},
    "preserve_threshold": {"gt": 0, "le": 1},
    "morphology_rounds": {"ge": 0, "le": MAX_ITERATIONS},
    "secondary_variance": {"ge": 0},
    "voxel_factor": {"gt": 0},
    "min_voxels_across": {"ge": 1, "le": 4096},
    "max_voxel_diagonal": {"ge": 0},
    "margin_voxels": {"ge": 0},
    "band_voxels": {"gt": 0, "le": 4096},  # a band wider than the largest grid is the whole grid
    "max_voxels": {"ge": 1, "le": MAX_GRID_VOXELS},
    "cut_voxels": {"ge": 0},
    "attach_conflict_voxels": {"ge": 0},
    "remesh_iterations": {"ge": 0, "le": MAX_ITERATIONS},
    "target_edge_factor": {"gt": 0},
    "taubin_iterations": {"ge": 0, "le": MAX_ITERATIONS},
    "plain_taubin_iterations": {"ge": 0, "le": MAX_ITERATIONS},
    "project_voxels": {"ge": 0},
    "fidelity_voxels": {"ge": 0},
    "fidelity_diagonal": {"ge": 0},
    "feature_rounds": {"ge": 0, "le": MAX_ITERATIONS},
    "refine_rounds": {"ge": 0, "le": MAX_ITERATIONS},
    "refine_min_edge": {"gt": 0},
    "fidelity_relax": {"gt": 0},
    "relax_max_angle_loss": {"ge": 0},
    "fold_free_deviation": {"ge": 0},
    "crease_ratio": {"ge": 0},
    "keep_input_corners": {},
    "min_angle_p05": {"ge": 0, "le": 60},
    "min_seam_wedge": {"ge": 0, "le": 360},
    "min_island_faces": {"ge": 0},
    "snap_input_vertices": {},
    "collapse_poor": {},
    "copy_coincident": {},
    "replaced_present": {},
    "retry_whole_region": {},
    "retry_max_faces": {"ge": 0},
    "bridge_recuts": {"ge": 0},
    "untangle_move": {"ge": 0},
    "crossing_rounds": {"ge": 0, "le": MAX_ITERATIONS},
    "shell_clearance_voxels": {"ge": 0, "le": 16},
    "backend": {},
    "keep_fields": {},
}

#: Types of the ``[fusion]`` options that :class:`rigmix.fusion.FusionParams` leaves loose.
FUSION_TYPES = {
    "fidelity_relax": tuple[float, ...],
    "backend": Literal["auto", "numpy", "numpy-igl", "openvdb"],  # rigmix.fusion.get_backend
}

#: Bounds of the ``[weights]`` options (:class:`rigmix.weights.WeightParams`).
WEIGHT_RANGES: dict[str, dict] = {
    "method": {},
    "max_influences": {"ge": 1, "le": 64},
    "match_distance": {"ge": 0},
    "match_angle": {"ge": 0, "le": 180},
    "match_on_surface": {"ge": 0},
    "min_confidence": {"ge": 0, "le": 1},
    "locality": {"ge": 0},
    "locality_power": {"gt": 0},
    "feature_field": {},
    "blend": {},
    "smoothing": {"ge": 0, "le": MAX_ITERATIONS},
    "seam_spread": {"ge": 0},
    "seam_rings": {"ge": 0, "le": MAX_ITERATIONS},
    "iterations": {"ge": 0, "le": MAX_ITERATIONS},
    "mirror_tol": {"ge": 0},
    "strength": {"ge": 0},
    "bone_prior": {"ge": 0, "le": 1},
    "ambient_borrow": {"ge": 0, "le": 1},
    "cut_joint_reach": {"ge": 0},
    "field_cache": {},
    "distill_options": {},
}

#: Bounds of the ``[animation]`` options (:class:`rigmix.animation.CompletionOptions`).
ANIMATION_RANGES: dict[str, dict] = {
    "clips": {},
    "sources": {},
    "fps": {"ge": 1, "le": MAX_FPS},  # below 1 fps a clip is one or two frames
    "rotation_weight": {"ge": 0},
    "translation_weight": {"ge": 0},
    "continuity": {"ge": 0},
    "hops_full": {"ge": 0, "le": MAX_ITERATIONS},
    "hops_max": {"ge": 0, "le": MAX_ITERATIONS},
    "metric": {},
    "jump_penalty": {"ge": 0},
    "smoothing": {"ge": 0, "le": MAX_ITERATIONS},
    "blend_frames": {"ge": 0, "le": MAX_ITERATIONS},
    "confidence_blend": {},
    "score_dtype": {},
    "fixed_frames": {},
    "rest_mismatch": {"ge": 0, "le": 180},
}

#: Bounds of the ``[gates]`` options (:class:`rigmix.gates.GateBounds`): up to a week.
GATE_RANGES: dict[str, dict] = {
    "max_seconds": {"gt": 0, "le": 7 * 86400},
}

_SCALARS = (bool, int, float, str)


def _bounded(tp, bounds: dict):
    """``tp`` with strict scalars (no ``"1"`` for 1, no 1.5 or true for an int) and ``bounds``
    on its number: a scalar, the scalar of an optional, or the items of ``tuple[X, ...]``."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp in _SCALARS:
        return Annotated[tp, Strict(), Field(**bounds)] if bounds else Annotated[tp, Strict()]
    if origin in (Union, types.UnionType):
        return Union[tuple(a if a is type(None) else _bounded(a, bounds) for a in args)]
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        return tuple[_bounded(args[0], bounds), ...]
    if bounds:
        raise TypeError(f"bounds {bounds} given for a {tp} option")
    return tp


def _attribute_docs(cls) -> dict[str, str]:
    """The description of each field in the ``Attributes`` section of ``cls``'s docstring.

    An entry is ``name[, name...] : text`` followed by indented lines. When every entry has
    indented lines (numpydoc), ``text`` is the type and the indented lines the description;
    otherwise the entry's text and its lines together are the description.
    """
    doc = inspect.getdoc(cls) or ""
    _, _, section = doc.partition("Attributes\n----------\n")
    entries = []  # (names, head, body lines)
    for line in section.splitlines():
        head = re.fullmatch(r"(\w+(?:, \w+)*) : (.*)", line)
        if head:
            entries.append((head.group(1).split(", "), head.group(2).strip(), []))
        elif line.startswith(" ") and entries:
            entries[-1][2].append(line.strip())
        elif line.strip():
            break  # the next section
    numpydoc = all(body for _, _, body in entries)
    out = {}
    for names, head, body in entries:
        text = " ".join(body if numpydoc else [head, *body])
        out.update(dict.fromkeys(names, text))
    return out


class _ParamsSection(BaseModel):
    """A config section with the fields of a stage's parameter dataclass (``PARAMS``)."""

    model_config = _STRICT
    PARAMS: ClassVar[type]

    def to_params(self):
        """The section as the stage's parameter dataclass (``PARAMS``)."""
        return self.PARAMS(**{name: getattr(self, name) for name in type(self).model_fields})

    @model_validator(mode="after")
    def _params_accept(self):
        try:  # the dataclass's own checks across fields (e.g. hops_max >= hops_full)
            self.to_params()
        except InputError as e:
            raise ValueError(str(e)) from None
        return self


def _section_model(name: str, params: type, bounds: dict[str, dict], types_: dict | None = None):
    """A :class:`_ParamsSection` named ``name`` with the fields of the dataclass ``params``:
    its types (or ``types_[field]``) made strict and bounded by ``bounds[field]``, its defaults,
    and the descriptions of its docstring."""
    hints = typing.get_type_hints(params)
    docs = _attribute_docs(params)
    fields = {}
    for f in dataclasses.fields(params):
        tp = _bounded((types_ or {}).get(f.name, hints[f.name]), bounds.get(f.name, {}))
        if f.default is dataclasses.MISSING:
            info = Field(default_factory=f.default_factory, description=docs.get(f.name))
        else:
            info = Field(f.default, description=docs.get(f.name))
        fields[f.name] = (tp, info)
    doc = f"The options of :class:`{params.__module__}.{params.__qualname__}`, checked at load."
    model = create_model(name, __base__=_ParamsSection, __doc__=doc, __module__=__name__, **fields)
    model.PARAMS = params
    return model


FusionOptions = _section_model("FusionOptions", FusionParams, FUSION_RANGES, FUSION_TYPES)
WeightOptions = _section_model("WeightOptions", WeightParams, WEIGHT_RANGES)
AnimationOptions = _section_model("AnimationOptions", CompletionOptions, ANIMATION_RANGES)
GateOptions = _section_model("GateOptions", GateBounds, GATE_RANGES)


class Config(BaseModel):
    """A composition: input characters and the actions on their skeletons.

    Buildable in code (``Config(characters={...}, actions=[...])``; relative paths then resolve
    against the current directory unless :meth:`with_base_dir` says otherwise) or read with
    :func:`load_config`.
    """

    model_config = _STRICT

    name: str = Field("composition", description="Name of the output character.")
    characters: dict[str, CharacterConfig] = Field(
        min_length=1, description="Input characters by id (the id is used by actions and reports).")
    actions: list[Action] = Field(default_factory=list, description="Actions, applied together.")
    mapping: MappingOptions = Field(default_factory=MappingOptions)
    positioning: PositioningOptions = Field(default_factory=PositioningOptions)
    fusion: FusionOptions = Field(default_factory=FusionOptions,
                                  description="Surface fusion options (rigmix.fusion.FusionParams).")
    weights: WeightOptions = Field(default_factory=WeightOptions,
                                   description="Skin weight options (rigmix.weights.WeightParams).")
    animation: AnimationOptions = Field(
        default_factory=AnimationOptions,
        description="Animation completion options (rigmix.animation.CompletionOptions); `fixed_frames` "
                    "is a list of tables with the fields of rigmix.animation.completion.FixedFrame.")
    gates: GateOptions = Field(default_factory=GateOptions,
                               description="Bounds of the hard gates of the report (rigmix.gates.GateBounds).")

    _base_dir: Path | None = PrivateAttr(default=None)
    _source: str = PrivateAttr(default="")

    @model_validator(mode="after")
    def _known_characters(self):
        ids = list(self.characters)
        for i, a in enumerate(self.actions):
            for key in ("source", "target"):
                cid = getattr(a, key, None)
                if cid is not None and cid not in self.characters:
                    raise ValueError(
                        f"actions[{i}].{key}: unknown character {cid!r}; "
                        f"known: {', '.join(ids)}{_closest_hint(cid, ids)}")
        return self

    @model_validator(mode="after")
    def _grid_fits(self):
        # cluster_grid reaches max(margin_voxels, cut_voxels + 4) voxels beyond the junction on
        # each side, whatever the voxel size: that many samples must fit in max_voxels
        f = self.fusion
        side = 2 * math.ceil(max(f.margin_voxels, f.cut_voxels + 4)) + 1
        if side ** 3 > f.max_voxels:
            raise ValueError(f"fusion: margin_voxels = {f.margin_voxels:g} and cut_voxels = {f.cut_voxels:g} need "
                             f"at least {side ** 3} voxels per junction grid, more than max_voxels = {f.max_voxels}; "
                             f"lower margin_voxels or cut_voxels")
        return self

    def with_options(self, **sections: dict) -> "Config":
        """A copy with options of the stage sections overridden, checked like the file's.

        ``config.with_options(weights={"method": "nearest"})`` keeps the other ``[weights]``
        options; the copy keeps the base folder and the source.

        Raises
        ------
        InputError
            Naming the section and key of an unknown option or an invalid value.
        """
        update = {}
        for name, options in sections.items():
            current = getattr(self, name)
            try:
                update[name] = type(current).model_validate({**current.model_dump(), **options})
            except ValidationError as e:
                raise InputError(f"config {self.source}: {_error_text(e, prefix=(name,))}") from None
        return self.model_copy(update=update)

    # -- where the config came from -------------------------------------------------------
    def with_base_dir(self, base_dir, source: str = "") -> "Config":
        """A copy whose relative paths resolve against ``base_dir`` (messages name ``source``)."""
        out = self.model_copy()
        out._base_dir = Path(base_dir)
        out._source = str(source)
        return out

    @property
    def base_dir(self) -> Path:
        """Folder that relative character paths resolve against."""
        return self._base_dir if self._base_dir is not None else Path.cwd()

    @property
    def source(self) -> str:
        """The config file (for messages), ``"<config>"`` when built in code."""
        return self._source or "<config>"

    def character_path(self, cid: str) -> Path | str:
        """Resolved path of character ``cid`` (a ``Path``), or the ``builtin:NAME`` string."""
        raw = self.characters[cid].path
        if raw.startswith(BUILTIN_PREFIX):
            return raw
        try:
            return expand_path(raw, self.base_dir)
        except KeyError as e:
            raise InputError(
                f"config {self.source}: characters.{cid}.path: environment variable {e.args[0]} "
                f"is not set (in {raw!r})") from None


#: ``${NAME}`` variables with a default: the folder of that name in ``../shared/data/`` beside the
#: repository (the shared test characters and the corpus)
DATA_DIRS = {"RIGMIX_ASSETS": "characters", "RIGMIX_CORPUS": "corpus"}


def default_data_dir(variable: str) -> Path:
    """``$variable``, else its :data:`DATA_DIRS` folder in ``../shared/data`` beside the repository."""
    env = os.environ.get(variable)
    if env:
        return Path(env)
    return Path(__file__).resolve().parent.parent.parent / "shared" / "data" / DATA_DIRS[variable]


def default_assets_dir() -> Path:
    """``$RIGMIX_ASSETS``, else ``../shared/data/characters`` beside the repository."""
    return default_data_dir("RIGMIX_ASSETS")


_VAR = re.compile(r"\$\{(\w+)\}")


def expand_path(raw: str, base_dir) -> Path:
    """Expand ``${VAR}`` and ``~`` in ``raw`` and resolve it against ``base_dir``.

    Raises ``KeyError(name)`` for an unset variable other than those of :data:`DATA_DIRS`.
    """

    def sub(m):
        name = m.group(1)
        if name in DATA_DIRS:
            return str(default_data_dir(name))
        if name not in os.environ:
            raise KeyError(name)
        return os.environ[name]

    p = Path(_VAR.sub(sub, raw)).expanduser()
    return p if p.is_absolute() else Path(base_dir) / p


def closest_names(name: str, names, n: int = 3) -> list[str]:
    """Up to ``n`` names of ``names`` closest to ``name`` (difflib), case-insensitive first."""
    names = list(names)
    exact = [x for x in names if x.lower() == name.lower()]
    close = difflib.get_close_matches(name, names, n=n, cutoff=0.5)
    out = []
    for x in exact + close:
        if x not in out:
            out.append(x)
    return out[:n]


def _closest_hint(name: str, names) -> str:
    close = closest_names(name, names)
    return f" (closest: {', '.join(close)})" if close else ""


_PLAIN_KEY = re.compile(r"[A-Za-z0-9_.\-]+")


def _loc(loc) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("attach", "replace", "remove") and out.startswith("actions"):
            continue  # the discriminated union's tag: not a key the user wrote
        elif isinstance(part, str) and not _PLAIN_KEY.fullmatch(part):
            out += f"[{json.dumps(part)}]"  # quoted: a key with spaces or newlines stays one line
        else:
            out += ("." if out else "") + str(part)
    return out


def _unwrap(tp):
    """``tp`` without ``Annotated`` and ``None`` in a union."""
    while True:
        if typing.get_origin(tp) is Annotated:
            tp = typing.get_args(tp)[0]
        elif typing.get_origin(tp) in (Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(args) != 1:
                return tp
            tp = args[0]
        else:
            return tp


def _keys_of(tp) -> list[str]:
    """The keys a model or dataclass type takes (none for another type)."""
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return list(tp.model_fields)
    if dataclasses.is_dataclass(tp):
        return [f.name for f in dataclasses.fields(tp)]
    return []


def _known_keys(loc) -> list[str]:
    """The keys known where a validation error located at ``loc`` found an unknown one."""
    tp = Config
    for part in loc[:-1]:
        tp = _unwrap(tp)
        origin, args = typing.get_origin(tp), typing.get_args(tp)
        if origin in (Union, types.UnionType):  # a discriminated union: ``part`` is the tag
            tp = next((a for a in args if part in typing.get_args(_unwrap(getattr(
                getattr(a, "model_fields", {}).get("op"), "annotation", None)))), None)
        elif origin in (dict, collections.abc.Mapping) and args:
            tp = args[-1]  # ``part`` is a key of the mapping
        elif origin in (list, tuple) and args:
            tp = args[0]  # ``part`` is an index
        elif isinstance(tp, type) and issubclass(tp, BaseModel) and part in tp.model_fields:
            tp = tp.model_fields[part].annotation
        elif dataclasses.is_dataclass(tp) and part in {f.name for f in dataclasses.fields(tp)}:
            tp = typing.get_type_hints(tp)[part]
        else:
            return []
    return _keys_of(_unwrap(tp))


def _error_text(err: ValidationError, prefix: tuple = ()) -> str:
    """One line naming each offending key (``prefix`` + pydantic's location) and the problem."""
    parts = []
    for e in err.errors():
        loc = _loc(prefix + tuple(e["loc"]))
        if e["type"] in ("extra_forbidden", "unexpected_keyword_argument"):
            key = prefix + tuple(e["loc"])
            parts.append(f"{loc}: unknown key{_closest_hint(str(key[-1]), _known_keys(key))}")
        else:
            msg = " ".join(e["msg"].removeprefix("Value error, ").splitlines())
            parts.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(parts)


def parse_config(data: dict, *, base_dir=None, source: str = "") -> Config:
    """Validate a config mapping (as read from TOML) into a :class:`Config`.

    Raises
    ------
    InputError
        Naming ``source`` and every offending key.
    """
    try:
        cfg = Config.model_validate(data)
    except ValidationError as e:
        raise InputError(f"config {source or '<config>'}: {_error_text(e)}") from None
    return cfg.with_base_dir(base_dir if base_dir is not None else Path.cwd(), source)


def load_config(path) -> Config:
    """Read and validate a composition config (TOML).

    Parameters
    ----------
    path : str or Path
        The ``.toml`` file; relative character paths resolve against its folder.

    Returns
    -------
    Config

    Raises
    ------
    InputError
        The file is missing or not TOML, a key is unknown or a value invalid, an action names an
        unknown character, or a character file does not exist.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"config: no such file {path}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"config: cannot read {path}: {e}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"config {path}: not valid TOML: {e}") from None
    except RecursionError:  # tomllib parses nested arrays and tables recursively
        raise InputError(f"config {path}: arrays or tables nested too deep to read; a composition "
                         "config needs a few levels") from None
    cfg = parse_config(data, base_dir=path.resolve().parent, source=str(path))
    check_files(cfg)
    return cfg


def check_files(cfg: Config) -> None:
    """Raise :class:`InputError` naming the key of the first character file that does not exist."""
    for cid in cfg.characters:
        p = cfg.character_path(cid)
        if isinstance(p, Path) and not p.is_file():
            raise InputError(
                f"config {cfg.source}: characters.{cid}.path: no such file {p} "
                f"(from {cfg.characters[cid].path!r}; set RIGMIX_ASSETS or RIGMIX_CORPUS for their ${{...}} paths)")


def config_schema() -> dict:
    """The JSON schema of :class:`Config` (what ``rigmix schema`` prints)."""
    return Config.model_json_schema()
