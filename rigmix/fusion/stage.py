"""The fusion stage of :func:`rigmix.pipeline.compose` (M_R), for ``register_stage``."""

from __future__ import annotations

import dataclasses
import logging

from ..errors import InputError
from .fuse import FusionParams, fuse_surfaces
from .inputs import fusion_inputs_from_plan

log = logging.getLogger(__name__)

__all__ = ["fusion_params", "fusion_stage"]


def fusion_params(options) -> FusionParams:
    """:class:`FusionParams` from the config's ``[fusion]`` table (``None``: defaults).

    Raises
    ------
    InputError
        An option that FusionParams does not have.
    """
    if not options:
        return FusionParams()
    known = {f.name for f in dataclasses.fields(FusionParams)}
    unknown = sorted(set(options) - known)
    if unknown:
        raise InputError(f"config [fusion]: unknown option(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    return FusionParams(**options)


def fusion_stage(composition, progress=None):
    """Fuse the positioned inputs' surfaces: ``stages["surface"]`` and ``report["fusion"]``.

    Parameters
    ----------
    composition : rigmix.pipeline.Composition
        After the operations and mapping stages.
    progress : callable, optional
        Unused (the pipeline reports the stage when it returns).

    Returns
    -------
    Composition
        With ``stages["surface"]`` a :class:`FusedSurface` (and ``stages["fusion_ids"]`` the
        character id of each fusion input) and ``report["fusion"]`` its report (``mesh``,
        ``fields``, ``timings``).
    """
    params = fusion_params(getattr(composition.config, "fusion", None))
    inputs, actions, ids = fusion_inputs_from_plan(composition.plan)
    surface = fuse_surfaces(inputs, actions, params=params)
    stages = {**composition.stages, "surface": surface, "fusion_ids": ids}
    report = {**composition.report, "fusion": surface.report}
    return dataclasses.replace(composition, stages=stages, report=report)
