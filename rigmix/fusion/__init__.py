"""Mesh fusion: the new surface M_R of a composition (PIPELINE.md section 3).

Entry point: :func:`fuse_surfaces` (plain numpy in, :class:`FusedSurface` out). The stages live
in their own modules: :mod:`.presence` (presence, secondary components, preserved faces),
:mod:`.fields` (local signed distance fields, numpy+libigl and OpenVDB backends, blending),
:mod:`.junction` (isosurface, cut, loop bridging), :mod:`.remesh` and :mod:`.report`.
"""

from typing import TYPE_CHECKING

from ..lazy import lazy_exports
from .params import FusionParams

if TYPE_CHECKING:
    from .fields import Grid, NumpyIglBackend, OpenVDBBackend, dump_fields, get_backend, import_openvdb
    from .fuse import FusedSurface, FusionAction, FusionInput, fuse_surfaces
    from .presence import compute_presence

__all__ = [
    "FusionInput", "FusionAction", "FusionParams", "FusedSurface", "fuse_surfaces",
    "compute_presence", "Grid", "NumpyIglBackend", "OpenVDBBackend", "get_backend", "import_openvdb",
    "dump_fields",
]

# the kernels (libigl, gpytoolbox, scipy) load on first use: a config needs only FusionParams
__getattr__, __dir__ = lazy_exports(__name__, {
    **dict.fromkeys(("Grid", "NumpyIglBackend", "OpenVDBBackend", "dump_fields", "get_backend", "import_openvdb"),
                    "fields"),
    **dict.fromkeys(("FusedSurface", "FusionAction", "FusionInput", "fuse_surfaces"), "fuse"),
    "compute_presence": "presence",
})
