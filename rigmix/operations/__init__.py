"""Operations (PIPELINE.md section 1): the config's actions turned into the output skeleton S_R.

Public entry: :func:`plan_operations` (:mod:`rigmix.operations.plan`), which resolves the
actions, builds S_R with provenance, matches scales and positions the inputs. The modules:

``plan``         actions -> output skeleton with provenance (:class:`Plan`)
``positioning``  scale matching and preliminary positioning of the inputs
``mirror``       reflecting a character across its symmetry plane, joint sides swapped
"""

from typing import TYPE_CHECKING

from ..lazy import lazy_exports

if TYPE_CHECKING:
    from .plan import FusedPair, Plan, ResolvedAction, plan_operations, resolve_actions, resolve_rotations

__all__ = ["plan_operations", "Plan", "FusedPair", "ResolvedAction", "resolve_actions", "resolve_rotations"]

# the positioning's solvers (scipy.sparse.linalg) load on first use: mirroring needs none of them
__getattr__, __dir__ = lazy_exports(__name__, dict.fromkeys(__all__, "plan"))
