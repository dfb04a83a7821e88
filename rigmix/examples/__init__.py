"""The built-in example characters, generated procedurally (no third-party assets).

Public entry: :func:`humanoid`, :func:`quadruped` and :func:`static_box`
(:mod:`rigmix.examples.characters`), named ``builtin:humanoid`` and ``builtin:quadruped`` in a
config. ``bodyplan`` is their signed-distance builder.
"""

from .characters import HUMANOID_JOINTS, QUADRUPED_JOINTS, humanoid, quadruped, static_box

__all__ = ["humanoid", "quadruped", "static_box", "HUMANOID_JOINTS", "QUADRUPED_JOINTS"]
