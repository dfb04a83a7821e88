"""dfd: Deep Feature Deformation weights for triangle meshes (standalone; never imports rigmix).

Method: PIPELINE.md section 6. Modules, in pipeline order:

- :mod:`dfd.render`: 24 views of a mesh; per pixel the triangle, barycentrics, shaded colour;
- :mod:`dfd.encoders` (and :mod:`dfd.dinov2`): images -> per-pixel unit features;
- :mod:`dfd.distill`: barycentric feature distillation into a :class:`dfd.field.FeatureField`;
- :mod:`dfd.weights`: handle weights (distance and cosine forms, constraints, geodesic locality);
- :mod:`dfd.symmetry`: mirror planes of the field;
- :mod:`dfd.deform`: linear blending with the simulated control point;
- :mod:`dfd.io`, :mod:`dfd.cli`: mesh files and the ``dfd`` command line.

Submodules are imported on demand (``from dfd.distill import distill``): ``import dfd`` alone
does not load torch.
"""

__version__ = "0.1.0"
