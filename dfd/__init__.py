"""dfd: Deep Feature Deformation weights for triangle meshes (standalone; never imports rigmix)."""

__version__ = "0.1.0"
