"""rigmix: compose new rigged, skinned and animated characters from pieces of existing ones."""

from .character import Anchor, Character, Clip, Material, Mesh, Prop, Skeleton, Texture, Track
from .errors import InputError, NumericalError, RigmixError, UnsupportedError

__version__ = "0.1.0"

__all__ = [
    "Anchor", "Character", "Clip", "Material", "Mesh", "Prop", "Skeleton", "Texture", "Track",
    "RigmixError", "InputError", "UnsupportedError", "NumericalError",
    "compose", "Composition", "Config", "load_config",
]

#: Public names imported on first use (``rigmix.compose`` pulls in scipy and the stages).
_LAZY = {"compose": "pipeline", "Composition": "pipeline", "Config": "config", "load_config": "config"}


def __getattr__(name):
    if name in _LAZY:
        from importlib import import_module

        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'rigmix' has no attribute {name!r}")
