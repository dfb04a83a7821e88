"""The options of the weights stage: the config's ``[weights]`` section.

:class:`rigmix.config.WeightOptions` is built from :class:`WeightParams` (its fields, defaults and
the descriptions below) and bounds its values at load.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

__all__ = ["WeightParams", "FILL_OPTION_NAMES"]

#: Fields of :class:`WeightParams` passed on to :func:`rigmix.weights.fill_weights` when set
#: (``None``: the fill method's own default).
FILL_OPTION_NAMES = ("iterations", "mirror_tol", "strength", "bone_prior", "field_cache", "distill_options")


@dataclass(frozen=True)
class WeightParams:
    """Parameters of :func:`rigmix.weights.blend_weights` (defaults: the project's ``dfd``).

    Attributes
    ----------
    method : {"nearest", "inpaint", "dfd"}
        Junction weight method (see :mod:`rigmix.weights.blend`).
    max_influences : int
        Non-zero weights per vertex, at least 1.
    match_distance : float
        Matching distance, a fraction of the bounding-box diagonal (``inpaint``, ``dfd``), >= 0.
    match_angle : float or None
        Matching normal angle, degrees in [0, 180]; ``None``: 30 for ``inpaint`` (the robust
        transfer paper), 90 for ``dfd``.
    match_on_surface : float or None
        Junction vertices within this fraction of the diagonal of their closest input point are
        matched whatever the normals; ``None``: :data:`rigmix.weights.blend.ON_SURFACE` for
        ``dfd``, 0 (off) otherwise.
    min_confidence : float
        Mapping confidence in [0, 1] below which a junction vertex is filled, never matched.
    locality : float
        ``dfd``: geodesic radius of a joint's reach, a fraction of the diagonal (0: off).
    locality_power : float
        ``dfd``: exponent of the locality's attenuation, > 0.
    feature_field : bool
        ``dfd``: distill the DFD feature field of the fused surface to judge the mirror prior
        (off by default: a few seconds for no measured gain; see :mod:`rigmix.weights.blend`).
    blend : {"paper", "harmonic"} or None
        Blend factors of the inputs' closest-point weights; ``None``: ``"harmonic"`` for
        ``dfd``, ``"paper"`` otherwise.
    smoothing : int
        Iterations of neighbour averaging on the junction vertices where the inputs disagree
        (0: none).
    seam_spread : float
        Disagreement (half L1 between the inputs' rows) above which ``smoothing`` applies.
    seam_rings : int
        Rings the smoothed seam grows by within the junction.
    iterations : int or None
        Post-smoothing iterations of the fill; ``None``: the junction's default
        (:data:`rigmix.weights.blend.JUNCTION_SMOOTHING` for ``dfd``, the fill's otherwise).
    mirror_tol : float or None
        ``dfd``: reflection distance tolerance of the mirror prior (``None``: the fill's).
    strength : float or None
        ``dfd``: weight of the prior's data term (``None``: the fill's).
    bone_prior : float or None
        ``dfd``: confidence of the skeleton's bone prior (``None``: the fill's).
    ambient_borrow : float
        ``dfd``: largest confidence of the prior borrowed, with the skeleton-relative field (no
        distillation), by junction vertices next to a joint whose weights no known vertex
        carries (0: off; :func:`rigmix.weights.ambient.ambient_borrow_prior`). On by default:
        issue 27's protocol 3 measured it 10.7% below the fill without a field, the one field
        use that passed the decision rule.
    cut_joint_reach : float
        An input's weights on a joint it does not keep (one a replace cut off) whose image in
        the output lies farther than this fraction of the input's bounding-box diagonal from it
        at rest go to the image of its nearest kept joint instead
        (:func:`rigmix.weights.retarget.cut_joints_to_nearest_kept`; 0: off). The bone map chose
        that image for the animation, and it can be a sibling of the kept part: a donor's crotch,
        painted on its right leg, gave the junction of its grafted left leg the body's right
        leg, and the two legs pull the seam apart in a walk. The default, 0.001, takes every
        image that is not where the joint is (an identity or a symmetric mirror composition
        keeps its map). Corpus matrix, against 0: the stretch gate fails on 5 cases instead of
        17 (a robot's leg replaced by a human's: ratio 15.7 to 0.0; the Wasp's mirrored
        foreleg 2.06 to 0.31), and no case that passed fails. With
        ``FusionParams.replaced_present`` False, the built-in centaur's junction covers the
        rider's waist, whose hips map onto the quadruped's hips at the other end of the horse:
        it stretched 3.2 times as much as the inputs under the walk, 0.63 times with 0.1.
    field_cache : str or None
        Folder caching distilled feature fields (``None``: no cache).
    distill_options : dict or None
        Distillation settings merged over :data:`rigmix.weights.blend.FIELD_DISTILL`.
    """

    method: Literal["nearest", "inpaint", "dfd"] = "dfd"
    max_influences: int = 4
    match_distance: float = 0.05
    match_angle: float | None = None
    match_on_surface: float | None = None
    min_confidence: float = 0.5
    locality: float = 0.1
    locality_power: float = 1.0
    feature_field: bool = False
    blend: Literal["paper", "harmonic"] | None = None
    smoothing: int = 0
    seam_spread: float = 0.1
    seam_rings: int = 2
    iterations: int | None = None
    mirror_tol: float | None = None
    strength: float | None = None
    bone_prior: float | None = None
    ambient_borrow: float = 0.5
    cut_joint_reach: float = 0.001
    field_cache: str | None = None
    distill_options: dict[str, Any] | None = None

    def fill_options(self) -> dict:
        """The fill options that are set, by name (for :func:`rigmix.weights.fill_weights`)."""
        return {n: getattr(self, n) for n in FILL_OPTION_NAMES if getattr(self, n) is not None}
