"""Skinning weights W_R (PIPELINE.md section 4).

Public entry: :func:`blend_weights` (the weights stage of :func:`rigmix.pipeline.compose`), in
:mod:`rigmix.weights.blend`. The modules:

``blend``     retargeting and the junction weights of a fused surface (W_R)
``fill``      :func:`fill_weights`: fill hidden or new rows (nearest, harmonic, inpaint, dfd)
``methods``   the nearest, harmonic and inpainting fills
``mirror``    the dfd fill: mirror and skeleton priors, the feature field
``locality``  geodesic locality of joints on a surface
``mesh``      welded Laplacians, solvers and sparsification
"""

from .blend import (BLEND_FACTORS, FIELD_DISTILL, JUNCTION_SMOOTHING, ON_SURFACE, WEIGHT_METHODS, SkinWeights,
                    blend_weights, closest_point_weights, retarget_weights, to_influences)
from .fill import FILL_METHODS, fill_weights
from .mesh import sparsify
from .params import WeightParams
from .mirror import Plane, feature_field, mirror_joints, symmetry_plane

__all__ = [
    "blend_weights", "WeightParams", "SkinWeights", "WEIGHT_METHODS", "BLEND_FACTORS", "ON_SURFACE",
    "JUNCTION_SMOOTHING",
    "FIELD_DISTILL", "retarget_weights", "closest_point_weights", "to_influences",
    "fill_weights", "FILL_METHODS", "sparsify", "feature_field", "mirror_joints", "symmetry_plane", "Plane",
]
