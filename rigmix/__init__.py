"""rigmix: compose new rigged, skinned and animated characters from pieces of existing ones."""

from .character import Anchor, Character, Clip, Material, Mesh, Prop, Skeleton, Texture, Track
from .errors import InputError, NumericalError, RigmixError, UnsupportedError

__version__ = "0.1.0"

__all__ = [
    "Anchor", "Character", "Clip", "Material", "Mesh", "Prop", "Skeleton", "Texture", "Track",
    "RigmixError", "InputError", "UnsupportedError", "NumericalError",
]
