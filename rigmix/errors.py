"""The few exceptions rigmix raises on purpose.

Every message names the stage, the file and the object, and what was expected, so that the CLI
can print it as one line and exit non-zero.
"""

from __future__ import annotations


class RigmixError(Exception):
    """Base class: anything rigmix reports to the user as a clear, one-line error."""


class InputError(RigmixError):
    """A file or config that cannot be read or is invalid (truncated GLB, unknown joint...)."""


class UnsupportedError(RigmixError):
    """Valid input that rigmix does not handle (e.g. a static glTF given to compose)."""


class NumericalError(RigmixError):
    """A numerical stage failed (singular system, empty isosurface...)."""
