"""The exceptions dfd raises on purpose.

Messages name the stage, the object and the fix, so that the CLI can print them as one line.
``dfd`` is standalone: these do not derive from rigmix's errors (rigmix may wrap them).
"""

from __future__ import annotations

__all__ = ["DfdError", "DfdInputError", "MissingCheckpointError"]


class DfdError(Exception):
    """Base class: anything dfd reports to the user as a clear, one-line error."""


class DfdInputError(DfdError, ValueError):
    """A mesh, file or argument that cannot be used (no faces, bad shape, unknown format...)."""


class MissingCheckpointError(DfdError, FileNotFoundError):
    """An encoder's weights are not on disk (dfd never downloads them)."""
