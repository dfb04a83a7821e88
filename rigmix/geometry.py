"""Small topology helpers shared by every stage (PIPELINE.md section 0).

glTF meshes are split at every UV, normal and material seam, and flat-shaded assets at every
face. Every topological operation (Laplacians, components, boundary loops, geodesics) runs on
the mesh welded by position, with the map back to the split vertices: :func:`weld` is
:func:`dfd.mesh.weld`, named here for the rigmix modules.

The input guards live here too: the native kernels (libigl, gpytoolbox, embree, SuperLU) may
crash the process on non-finite or astronomically large coordinates, and the writers must not
put NaN or infinity in a file, so every stage that hands numbers on checks them first with
:func:`check_coordinates`, :func:`check_transforms` and :func:`check_float32`, vectorized, and
raises :class:`rigmix.errors.InputError` naming the object and the fix.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from dfd.mesh import weld

from .errors import InputError

__all__ = ["bounding_box_diagonal", "closest_points", "closest_surface_points", "neighbour_roughness", "weld",
           "MAX_COORDINATE", "MAX_COORDINATE_RATIO", "MAX_GRID_VOXELS", "FLOAT32_MAX", "check_coordinates",
           "check_transforms", "check_unmirrored", "check_float32", "check_grid_voxels"]

#: Largest coordinate, in metres from the origin, that the geometry kernels are given: 1000 km,
#: beyond any character; float32 output positions there are still spaced 6 cm apart, and squared
#: distances (1e12) stay far from overflow in the native kernels.
MAX_COORDINATE = 1e6

#: Largest coordinate, in multiples of the characters' combined bounding-box diagonal: float32
#: output positions at that distance are spaced about 1e-3 of the characters' size apart, and a
#: signed distance field or a closest-point query still resolves the characters.
MAX_COORDINATE_RATIO = 1e4

#: Most samples one fusion grid may hold (:func:`rigmix.fusion.seams.cluster_grid`): 16M float64
#: samples are 128 MiB per field, four times the default ``[fusion] max_voxels``; a few fields
#: are alive at once, which keeps the fusion well under 2 GB.
MAX_GRID_VOXELS = 16_000_000

#: Largest finite float32 (glTF accessors and JSON numbers, USD float arrays).
FLOAT32_MAX = float(np.finfo(np.float32).max)

#: A linear part whose smallest singular value is below this fraction of its largest is singular
#: (zero scale, zero matrix, a projection).
_SINGULAR = 1e-9


def bounding_box_diagonal(V) -> float:
    """Length of the axis-aligned bounding box diagonal of points ``(n, 3)``."""
    V = np.asarray(V, dtype=np.float64)
    if len(V) == 0:
        return 0.0
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))


def closest_points(Q, V, F, reach=None):
    """Closest points of ``Q`` on the triangles ``F`` over ``V`` (libigl's exact query).

    With ``reach``, the faces whose bounding boxes come within ``reach`` of the queries' box are
    asked first: they answer every query whose closest point they hold within ``reach`` (any other
    face is farther), and the whole surface answers the rest. The tree of a whole input surface
    costs far more to build than a junction's few queries.

    Parameters
    ----------
    Q : (q, 3) float array
        Query points.
    V : (n, 3) float array
    F : (m, 3) int array
        At least one face.
    reach : float, optional
        Distance (same units) within which the near faces are gathered; None: the whole surface.

    Returns
    -------
    d2 : (q,) float64
        Squared distances.
    face : (q,) int64
        Rows of ``F``.
    C : (q, 3) float64
        Closest points.
    """
    import igl

    Q = np.ascontiguousarray(Q, dtype=np.float64).reshape(-1, 3)
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64).reshape(-1, 3)
    if len(Q) == 0:
        return np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3))
    near = np.arange(len(F))
    if reach is not None:
        T = V[F]
        lo, hi = Q.min(axis=0) - reach, Q.max(axis=0) + reach
        near = np.flatnonzero(np.all(T.min(axis=1) <= hi, axis=1) & np.all(T.max(axis=1) >= lo, axis=1))
    if len(near) == len(F) or not len(near):
        d2, face, C = igl.point_mesh_squared_distance(Q, V, F)
        return np.asarray(d2, np.float64), np.asarray(face, np.int64), np.asarray(C, np.float64)
    d2, face, C = igl.point_mesh_squared_distance(Q, V, np.ascontiguousarray(F[near]))
    d2, C = np.array(d2, np.float64), np.array(C, np.float64)
    face = near[np.asarray(face, np.int64)]
    far = np.flatnonzero(d2 > reach * reach)
    if len(far):
        d2[far], face[far], C[far] = igl.point_mesh_squared_distance(np.ascontiguousarray(Q[far]), V, F)
    return d2, face, C


def closest_surface_points(Q, V, F):
    """The closest point of a triangle mesh to each query point.

    Parameters
    ----------
    Q : (q, 3) float array
        Query points.
    V : (n, 3) float array
    F : (m, 3) int array
        At least one face.

    Returns
    -------
    distance : (q,) float64
    face : (q,) int64
        The face holding the closest point.
    bary : (q, 3) float64
        Its barycentric coordinates in that face: non-negative, summing to 1 (a degenerate face
        gives its corners 1/3 each).
    """
    import igl

    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64).reshape(-1, 3)
    d2, face, C = closest_points(Q, V, F)
    if len(face) == 0:
        return np.zeros(0), face, np.zeros((0, 3))
    T = F[face]
    B = igl.barycentric_coordinates(C, V[T[:, 0]], V[T[:, 1]], V[T[:, 2]])
    B = np.clip(np.nan_to_num(B, nan=1 / 3), 0, 1)
    B /= np.maximum(B.sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(np.maximum(d2, 0.0)), np.asarray(face, np.int64), B


def neighbour_roughness(A, X):
    """Half the L1 distance from each row of ``X`` to the mean of its neighbours' rows.

    Parameters
    ----------
    A : (k, k) scipy.sparse matrix
        Adjacency of the rows; any positive entry is an edge (its value is not used), no
        self-loops.
    X : (k, c) float array or scipy.sparse matrix
        Rows summing to 1 (skinning weights): the figure is in ``[0, 1]``, 1 for a row sharing
        nothing with its neighbours. Sparse: the same floats, dense a block of rows at a time
        (:func:`rigmix.sparse_weights.row_blocks`).

    Returns
    -------
    roughness : (k,) float64
        0 for a row without neighbours.
    has_neighbours : (k,) bool
    """
    import scipy.sparse as sp

    from .sparse_weights import row_blocks

    A = (A > 0).astype(np.float64)
    deg = np.asarray(A.sum(axis=1)).ravel()
    if not sp.issparse(X):
        mean = (A @ X) / np.maximum(deg, 1)[:, None]
        return np.where(deg > 0, 0.5 * np.abs(X - mean).sum(axis=1), 0.0), deg > 0
    X = X.tocsr()
    AX = (A @ X).tocsr()  # the neighbours' sums, in the order the dense product adds them
    r = np.zeros(X.shape[0])
    for rows in row_blocks(X.shape[0], X.shape[1]):
        mean = AX[rows].toarray() / np.maximum(deg[rows], 1)[:, None]
        r[rows] = 0.5 * np.abs(X[rows].toarray() - mean).sum(axis=1)
    return np.where(deg > 0, r, 0.0), deg > 0


def check_coordinates(points: Mapping, *, where: str, fix: str) -> float:
    """Check points before they reach a native geometry kernel.

    Every coordinate must be finite, within :data:`MAX_COORDINATE` of the origin, and within
    :data:`MAX_COORDINATE_RATIO` times the diagonal of the bounding box of all the points (when
    that diagonal is not 0).

    Parameters
    ----------
    points : mapping of str -> (n, 3) float array
        Points by the object they belong to (``"character 'donor' mesh vertices"``); empty
        arrays are skipped.
    where : str
        Start of the message (stage and file).
    fix : str
        What to change, appended to the message.

    Returns
    -------
    diagonal : float
        The bounding-box diagonal of all the points (0 without points).

    Raises
    ------
    InputError
        Naming the first object out of range.
    """
    boxes = {}
    for name, P in points.items():
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        if len(P) == 0:
            continue
        lo, hi = P.min(axis=0), P.max(axis=0)  # NaN propagates through min and max
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise InputError(f"{where}: {name} has non-finite coordinates (NaN or infinity); {fix}")
        far = float(max(np.abs(lo).max(), np.abs(hi).max()))
        if far > MAX_COORDINATE:
            raise InputError(f"{where}: {name} reaches {far:.3g} m from the origin, beyond the limit of "
                             f"{MAX_COORDINATE:.0e} m; {fix}")
        boxes[name] = (lo, hi, far)
    if not boxes:
        return 0.0
    lo = np.min([b[0] for b in boxes.values()], axis=0)
    hi = np.max([b[1] for b in boxes.values()], axis=0)
    diagonal = float(np.linalg.norm(hi - lo))
    for name, (_, _, far) in boxes.items():
        if diagonal > 0 and far > MAX_COORDINATE_RATIO * diagonal:  # points all at one place: no size
            raise InputError(f"{where}: {name} lies {far:.3g} from the origin, more than {MAX_COORDINATE_RATIO:.0e} "
                             f"times the size of everything composed ({diagonal:.3g}); {fix}")
    return diagonal


def check_transforms(M, names, *, where: str, what: str, fix: str) -> None:
    """Check affine matrices that will be inverted: finite and not singular.

    Parameters
    ----------
    M : (J, 4, 4) float array
        Column-vector affine matrices (rest world or inverse bind matrices).
    names : sequence of str
        The name of each matrix's joint, for the message.
    where, what, fix : str
        Message parts: ``"{where}: joint 'X' {what} is singular ...; {fix}"``.

    Raises
    ------
    InputError
        Naming the first joint whose matrix has a non-finite entry or a linear part whose
        smallest singular value is below 1e-9 of its largest (a zero scale, a zero matrix).
    """
    M = np.asarray(M, dtype=np.float64).reshape(-1, 4, 4)
    if len(M) == 0:
        return
    finite = np.isfinite(M).all(axis=(1, 2))
    bad = np.flatnonzero(~finite)
    if len(bad):
        raise InputError(f"{where}: joint {names[bad[0]]!r} {what} has NaN or infinite entries; {fix}")
    sv = np.linalg.svd(M[:, :3, :3], compute_uv=False)  # (J, 3), largest first
    with np.errstate(invalid="ignore", over="ignore"):
        singular = ~(sv[:, 2] > _SINGULAR * sv[:, 0])
    bad = np.flatnonzero(singular)
    if len(bad):
        raise InputError(f"{where}: joint {names[bad[0]]!r} {what} is singular (a zero scale or a zero "
                         f"matrix) and cannot be inverted; {fix}")


def check_unmirrored(M, names, *, where: str, what: str) -> None:
    """Refuse a joint matrix that mirrors (a negative determinant: a negative scale, on the joint
    or above it).

    A composed skeleton has unit-scale joints (Blender bones hold no rest scale), so a mirroring
    can only be baked into the mesh and inverse bind matrices; that keeps the rest pose, but the
    joint's clips then turn the other way (a mirrored Fox joint put its skinned vertices half the
    bounding-box diagonal off in the identity composition).

    Parameters
    ----------
    M : (J, 4, 4) float array
        Column-vector affine matrices, finite (rest world or inverse bind matrices).
    names : sequence of str
        The name of each matrix's joint, for the message.
    where, what : str
        Message parts: ``"{where}: joint 'X' {what} mirrors ..."``.

    Raises
    ------
    InputError
        Naming the first mirrored joint and the fix.
    """
    M = np.asarray(M, dtype=np.float64).reshape(-1, 4, 4)
    bad = np.flatnonzero(np.linalg.det(M[:, :3, :3]) < 0) if len(M) else []
    if len(bad):
        raise InputError(f"{where}: joint {names[bad[0]]!r} {what} mirrors (a negative scale on the joint or a "
                         "parent), which a rigmix skeleton cannot hold: apply the scale to the mesh in the "
                         "exporter (Blender: Apply Scale) so that no joint has a negative scale")


def check_float32(values, what: str, *, dtype=np.float32) -> np.ndarray:
    """``values`` cast to ``dtype``, checked finite there (no NaN, nothing beyond its range).

    Parameters
    ----------
    values : float array, any shape
    what : str
        The message, naming the file and the object (``"write_gltf: out.glb: mesh 'Body'
        POSITION"``).
    dtype : numpy float dtype
        float32 (glTF, USD float arrays) or float16 (USD half scales).

    Returns
    -------
    array of ``dtype``

    Raises
    ------
    InputError
        A NaN, an infinity, or a value beyond the largest finite ``dtype`` (``|x| > 3.4e38`` for
        float32), with the first offending value.
    """
    a = np.asarray(values)
    with np.errstate(over="ignore", invalid="ignore"):
        out = a.astype(dtype)
    ok = np.isfinite(out)
    if not ok.all():
        first = np.asarray(a).reshape(-1)[np.flatnonzero(~ok.reshape(-1))[0]]
        limit = float(np.finfo(dtype).max)
        raise InputError(f"{what} holds {float(first):.4g}, not a finite {np.dtype(dtype).name} "
                         f"(|x| <= {limit:.4g}, no NaN): the value that produced it is out of range")
    return out


def check_grid_voxels(shape, *, where: str, limit: int) -> None:
    """Refuse a sampling grid of ``shape`` with more than ``min(limit, MAX_GRID_VOXELS)`` samples,
    before anything is allocated (the count is exact, in Python integers)."""
    cap = min(int(limit), MAX_GRID_VOXELS)
    count = math.prod(int(n) for n in shape)
    if count > cap or min(int(n) for n in shape) <= 0:
        raise InputError(f"{where}: the grid would hold {count:.3g} voxels ({' x '.join(map(str, shape))}), more "
                         f"than the limit of {cap}; lower [fusion] margin_voxels, cut_voxels or min_voxels_across, "
                         f"or raise voxel_factor ([fusion] max_voxels is at most {MAX_GRID_VOXELS})")
