"""Animation (PIPELINE.md section 5): clip sampling and animation completion A_R.

Public entry: :func:`complete_clips` (:mod:`rigmix.animation.completion`), the completion
stage. The modules:

``sampling``     clip sampling (LINEAR, STEP, CUBICSPLINE) and resampling
``keyframes``    keyframe scores: forward kinematics, pose mapping, continuity
``transitions``  frame choice and seam blending
``completion``   completing every clip for the output skeleton
``fidelity``     how closely the output clips replay each input's own joints (the report's
                 ``animation.fidelity_max``)
"""

from .completion import CompletionOptions, complete_clips
from .sampling import clip_times, resample_clip, sample_clip, sample_track

__all__ = ["complete_clips", "CompletionOptions", "sample_track", "sample_clip", "clip_times", "resample_clip"]
