"""Skinning weights W_R (PIPELINE.md section 4).

Public entry: :func:`blend_weights` (the weights stage of :func:`rigmix.pipeline.compose`), in
:mod:`rigmix.weights.blend`. The modules:

``retarget``  input weights onto the output joints, closest-point weights, influences
``blend``     the junction weights of a fused surface (W_R), step by step
``junction``  junction operators: matching, harmonic blend factors, continuation of far parts
``fill``      :func:`fill_weights`: fill hidden or new rows (nearest, harmonic, inpaint, dfd)
``methods``   the nearest, harmonic and inpainting fills
``mirror``    the dfd fill: mirror and skeleton priors, the feature field
``locality``  geodesic locality of joints on a surface
``mesh``      welded Laplacians, solvers and sparsification
``params``    :class:`WeightParams`, the ``[weights]`` options
"""

from typing import TYPE_CHECKING

from ..lazy import lazy_exports
from .params import WeightParams

if TYPE_CHECKING:
    from .blend import (
        BLEND_FACTORS,
        FIELD_DISTILL,
        JUNCTION_SMOOTHING,
        ON_SURFACE,
        WEIGHT_METHODS,
        JunctionBlend,
        SkinWeights,
        blend_junction,
        blend_weights,
        copy_preserved_rows,
        junction_fill_options,
        match_junction_rows,
        smooth_seam,
        weights_report,
    )
    from .fill import FILL_METHODS, fill_weights
    from .mesh import sparsify
    from .mirror import Plane, feature_field, mirror_joints, symmetry_plane
    from .retarget import blend_parts, closest_point_weights, retarget_inputs, retarget_weights, to_influences

__all__ = [
    "blend_weights", "WeightParams", "SkinWeights", "WEIGHT_METHODS", "BLEND_FACTORS", "ON_SURFACE",
    "JUNCTION_SMOOTHING", "FIELD_DISTILL", "retarget_weights", "retarget_inputs", "closest_point_weights",
    "blend_parts", "to_influences", "copy_preserved_rows", "junction_fill_options", "JunctionBlend",
    "blend_junction", "match_junction_rows", "smooth_seam", "weights_report", "fill_weights", "FILL_METHODS",
    "sparsify", "feature_field", "mirror_joints", "symmetry_plane", "Plane",
]

# the solvers and the feature field load on first use: a config needs only WeightParams
__getattr__, __dir__ = lazy_exports(__name__, {
    **dict.fromkeys(("BLEND_FACTORS", "FIELD_DISTILL", "JUNCTION_SMOOTHING", "ON_SURFACE", "WEIGHT_METHODS",
                     "JunctionBlend", "SkinWeights", "blend_junction", "blend_weights", "copy_preserved_rows",
                     "junction_fill_options", "match_junction_rows", "smooth_seam", "weights_report"), "blend"),
    **dict.fromkeys(("FILL_METHODS", "fill_weights"), "fill"),
    "sparsify": "mesh",
    **dict.fromkeys(("Plane", "feature_field", "mirror_joints", "symmetry_plane"), "mirror"),
    **dict.fromkeys(("blend_parts", "closest_point_weights", "retarget_inputs", "retarget_weights", "to_influences"),
                    "retarget"),
})
