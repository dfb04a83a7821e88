"""Image encoders: images -> per-pixel unit feature vectors (PIPELINE.md section 6).

Every encoder follows :class:`Encoder`: a ``feature_dim`` and ``encode(images)`` mapping
``(B, H, W, 3)`` float32 images in [0, 1] to ``(B, H, W, C)`` float32 features, L2-normalized
per pixel. Encoders that can use more than colour (the rendered normals and depth) also have
``encode_views(views)``; :func:`encode_views` calls it when present.

- ``"filterbank"`` (:class:`FilterBankEncoder`, default): needs no weights, so the whole
  pipeline runs offline. Hand-made responses of the shaded render (colour, gradient magnitude
  and orientation at several scales) plus the normal and depth channels of the render.
- ``"skeleton"`` (:class:`SkeletonEncoder`): where each pixel's surface point sits relative to the
  bones (given as segments): the point in the frames of its nearest bones, and which bones.
- ``"hks"`` (:class:`HeatKernelEncoder`): the heat kernel signature of each pixel's surface point,
  from a few eigenpairs of the mesh's cotangent Laplacian (intrinsic geometry).
- :class:`CombinedEncoder`: several encoders side by side (e.g. skeleton and filter bank).
- ``"dinov2"`` (:class:`dfd.dinov2.DinoV2Encoder`): DINOv2 ViT patch tokens, upsampled, from a
  local checkpoint; dfd never downloads weights.
"""

from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from scipy import ndimage

from dfd.errors import DfdInputError

if TYPE_CHECKING:
    # Seen by linters and type checkers only; at run time the module ``__getattr__`` below
    # imports it on first access, because dfd.dinov2 needs torch.
    from dfd.dinov2 import DinoV2Encoder

__all__ = ["Encoder", "FilterBankEncoder", "PointEncoder", "SkeletonEncoder", "HeatKernelEncoder", "CombinedEncoder",
           "DinoV2Encoder", "get_encoder", "encode_views", "view_points", "bone_segments", "point_field", "ENCODERS"]


@runtime_checkable
class Encoder(Protocol):
    """What the distillation needs from an image encoder."""

    feature_dim: int

    def encode(self, images: np.ndarray) -> np.ndarray:
        """``(B, H, W, 3)`` float32 in [0, 1] -> ``(B, H, W, feature_dim)`` float32, unit rows."""
        ...


def _unit(X, eps=1e-12):
    """Rows of the last axis scaled to unit length (zero rows stay zero)."""
    n = np.linalg.norm(X, axis=-1, keepdims=True)
    return (X / np.maximum(n, eps)).astype(np.float32)


class FilterBankEncoder:
    """Multi-scale filter responses of the shaded render, plus its normals and depth.

    Channels (28), each standardized over the covered pixels of the batch, then weighted so that
    the three groups (colour, gradients, geometry) carry total variances in the ratio of the
    squared group weights (1 : 1 : 4 by default), then L2-normalized per pixel:

    - colour: RGB blurred at Gaussian scales ``0, 2, 4`` px (9);
    - gradients: at scales ``2, 4, 8`` px, the luminance gradient magnitude and the oriented
      energies ``|g_x|``, ``|g_y|``, ``max`` and ``min`` of ``|g_x +- g_y| / sqrt 2`` (15). The
      diagonal pair is sorted so that the responses do not change when the image is mirrored:
      a mirror-symmetric shape then gets mirror-symmetric features, which symmetry detection needs;
    - geometry (``encode_views`` only, zero in ``encode``): the absolute value of each component of
      the world normal (3; absolute for the same reason) and the camera distance minus the camera
      radius (1).

    Parameters
    ----------
    colour_scales, gradient_scales : tuple of float
        Gaussian standard deviations in pixels at 224 px; scaled with the image size.
    group_weights : (3,) floats
        Relative weights of the colour, gradient and geometry groups. The defaults (coarse
        gradients, geometry weighted 2) were chosen on a mirror-symmetric test figure: finer
        gradient scales and equal weights leave more view-dependent noise in the distilled field
        (mean mirror feature distance 0.093 against 0.082 after 300 steps at 64 px).
    """

    name = "filterbank"

    def __init__(self, colour_scales=(0.0, 2.0, 4.0), gradient_scales=(2.0, 4.0, 8.0), group_weights=(1.0, 1.0, 2.0)):
        self.colour_scales = tuple(float(s) for s in colour_scales)
        self.gradient_scales = tuple(float(s) for s in gradient_scales)
        self.group_weights = tuple(float(w) for w in group_weights)
        self.feature_dim = 3 * len(self.colour_scales) + 5 * len(self.gradient_scales) + 4

    def settings(self) -> dict:
        """Everything that changes the features (stored with distilled fields)."""
        return {
            "name": self.name,
            "colour_scales": list(self.colour_scales),
            "gradient_scales": list(self.gradient_scales),
            "group_weights": list(self.group_weights),
        }

    def _image_channels(self, images):
        """Colour and gradient channels ``(B, H, W, 9 + 15)`` float32 (unstandardized)."""
        B, H, W, _ = images.shape
        k = H / 224.0  # scales are given at 224 px
        out = []
        for s in self.colour_scales:
            out.append(images if s == 0 else ndimage.gaussian_filter(images, sigma=(0, s * k, s * k, 0)))
        lum = images @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
        for s in self.gradient_scales:
            sk = max(s * k, 0.5)
            gx = ndimage.gaussian_filter(lum, sigma=(0, sk, sk), order=(0, 0, 1))
            gy = ndimage.gaussian_filter(lum, sigma=(0, sk, sk), order=(0, 1, 0))
            diag = np.abs(gx + gy) / np.sqrt(2.0)
            anti = np.abs(gx - gy) / np.sqrt(2.0)
            out.append(
                np.stack(
                    [np.hypot(gx, gy), np.abs(gx), np.abs(gy), np.maximum(diag, anti), np.minimum(diag, anti)], axis=-1
                )
                * (sk)  # scale-normalized derivatives
            )
        return np.concatenate(out, axis=-1).astype(np.float32)

    def _finish(self, raw, mask, n_geometry):
        """Standardize over covered pixels, weight the groups, L2-normalize."""
        sel = raw[mask] if mask.any() else raw.reshape(-1, raw.shape[-1])
        mean = sel.mean(axis=0)
        std = sel.std(axis=0)
        X = (raw - mean) / np.where(std > 1e-8, std, 1.0)
        n_colour = 3 * len(self.colour_scales)
        n_grad = 5 * len(self.gradient_scales)
        groups = [(0, n_colour), (n_colour, n_colour + n_grad), (n_colour + n_grad, n_colour + n_grad + 4)]
        for (a, b), w in zip(groups, self.group_weights):
            X[..., a:b] *= w / np.sqrt(b - a)
        if n_geometry == 0:
            X[..., groups[2][0] :] = 0.0
        X[~mask] = 0.0
        return _unit(X)

    def encode(self, images):
        """Features of images alone (the geometry channels are zero).

        Parameters
        ----------
        images : (B, H, W, 3) float array in [0, 1]
            Pure white pixels are treated as background for the standardization.

        Returns
        -------
        (B, H, W, feature_dim) float32, unit rows on foreground pixels, zero on background.
        """
        images = _check_images(images)
        raw = np.concatenate([self._image_channels(images), np.zeros(images.shape[:3] + (4,), np.float32)], axis=-1)
        mask = (images < 1.0).any(axis=-1)
        return self._finish(raw, mask, 0)

    def encode_views(self, views):
        """Features of rendered views, with their normal and depth channels.

        Parameters
        ----------
        views : dfd.render.Views

        Returns
        -------
        (B, H, W, feature_dim) float32, unit rows on covered pixels, zero on background.
        """
        images = _check_images(views.rgb)
        mask = views.mask
        radius = np.linalg.norm(views.cameras.eye, axis=1)[:, None, None]
        depth = np.where(mask, views.depth - radius, 0.0)[..., None]
        raw = np.concatenate(
            [self._image_channels(images), np.abs(views.normals), depth.astype(np.float32)], axis=-1
        )
        return self._finish(raw, mask, 4)


def _check_images(images):
    images = np.asarray(images, dtype=np.float32)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise DfdInputError(f"encoder: images must be (B, H, W, 3), got shape {images.shape}")
    return images


def encode_views(encoder, views):
    """Per-pixel features of rendered views with any encoder: ``encode_views`` when it has one,
    else ``encode`` of the shaded colours. Returns ``(B, H, W, C)`` float32."""
    if hasattr(encoder, "encode_views"):
        return encoder.encode_views(views)
    return encoder.encode(views.rgb)


def view_points(views):
    """The surface point of every pixel of rendered views, in mesh coordinates.

    From each pixel's ray and its hit distance (``views.depth``), so it needs neither the
    rendered mesh nor its faces.

    Parameters
    ----------
    views : dfd.render.Views

    Returns
    -------
    (B, H, W, 3) float64
        Mesh coordinates of the hit points; zero on background pixels.
    """
    origins, directions = views.cameras.rays()
    P = origins + views.depth[..., None].astype(np.float64) * directions
    P = views.cameras.normalization.invert(P.reshape(-1, 3)).reshape(P.shape)
    P[~views.mask] = 0.0
    return P


def bone_segments(positions, parents):
    """The bones of a skeleton as segments, from each joint to each of its children.

    Parameters
    ----------
    positions : (J, 3) float array
        Joint positions (bind pose, in the mesh's coordinates).
    parents : (J,) int array
        Parent index of each joint, ``-1`` at a root.

    Returns
    -------
    heads, tails : (S, 3) float64 each
        Segment ends (parent joint, child joint); a skeleton of one joint gives one
        zero-length segment at it.
    """
    P = np.asarray(positions, dtype=np.float64)
    parents = np.asarray(parents, dtype=np.int64).reshape(-1)
    if P.ndim != 2 or P.shape[1] != 3 or len(parents) != len(P) or len(P) == 0:
        raise DfdInputError(f"bone_segments: need positions (J, 3) and parents (J,), got {P.shape} and {parents.shape}")
    child = np.flatnonzero(parents >= 0)
    if len(child) == 0:
        return P[:1].copy(), P[:1].copy()
    return P[parents[child]].copy(), P[child].copy()


def _standardize(raw, mask, groups):
    """Channels standardized over the covered pixels, each group ``(start, stop, weight)``
    scaled to total variance ``weight**2``, background zero, rows L2-normalized."""
    sel = raw[mask] if mask.any() else raw.reshape(-1, raw.shape[-1])
    std = sel.std(axis=0)
    X = (raw - sel.mean(axis=0)) / np.where(std > 1e-8, std, 1.0)
    for a, b, w in groups:
        X[..., a:b] *= w / np.sqrt(b - a)
    X[~mask] = 0.0
    return _unit(X)


class PointEncoder:
    """An encoder of surface points (:meth:`point_features` of ``(n, 3)`` points, defined by the
    subclass with ``name``, ``feature_dim`` and ``channel_groups``): a rendered view is encoded at
    each covered pixel's surface point (:func:`view_points`); images alone carry no points."""

    def encode(self, images):
        """Not available: the features need the surface points of :meth:`encode_views`."""
        raise DfdInputError(f"{self.name} encoder: needs rendered views with depth (encode_views), not images alone")

    def encode_views(self, views):
        """Features of rendered views.

        Returns
        -------
        (B, H, W, feature_dim) float32, unit rows on covered pixels, zero on background.
        """
        mask = views.mask
        raw = np.zeros(mask.shape + (self.feature_dim,), dtype=np.float64)
        raw[mask] = self.point_features(view_points(views)[mask])
        return _standardize(raw, mask, self.channel_groups)


class SkeletonEncoder(PointEncoder):
    """Where each rendered surface point sits relative to the skeleton's bones.

    The features of a pixel depend on its surface point only (:func:`view_points`), not on the
    shading: what part of the body it is on, which an image encoder without part semantics does
    not know. For each of the ``nearest`` bones closest to the point (nearest first), 12
    channels:

    - the point in the bone's frame: position along the bone ``t`` (0 at the head, 1 at the
      tail, clipped to ``[-0.5, 1.5]``), distance around it relative to the bone's length
      ``d / (d + L)``, relative to the skeleton's extent ``d / E``, and the angle around it as
      ``cos`` and ``|sin|`` (the frame's first axis is the world axis least aligned with the
      bone, made orthogonal to it; ``|sin|`` so that a mirror image gets the same features);
    - the bone itself: length ``L / E``, the absolute direction components (3), and the
      absolute offset of its midpoint from the skeleton's bounding-box centre over ``E`` (3):
      which bone it is, told apart from the others, equal on a bone and its mirror image across
      an axis plane through the centre.

    Channels are standardized over the covered pixels; the bone of rank ``r`` (0 nearest) is
    weighted ``1 / (r + 1)``; rows are L2-normalized. ``E`` is the bounding-box diagonal of the
    bone ends.

    Parameters
    ----------
    heads, tails : (S, 3) float arrays
        Bone segments in the mesh's coordinates (:func:`bone_segments` from joint positions and
        parents). A zero-length segment is a point.
    nearest : int
        Bones described per point.
    describe : bool
        Include the 7 channels that describe each bone (which bone it is); without them only
        the point's place relative to its bones remains (5 channels per bone), alike on every
        bone: what a profile borrowed from another joint needs.
    chunk : int
        Points per block of the distance computation (memory: ``chunk * S`` floats).
    """

    name = "skeleton"
    #: channels per described bone
    CHANNELS = 12

    def __init__(self, heads, tails, *, nearest=2, describe=True, chunk=65536):
        H = np.asarray(heads, dtype=np.float64)
        T = np.asarray(tails, dtype=np.float64)
        if H.ndim != 2 or H.shape[1] != 3 or H.shape != T.shape or len(H) == 0:
            raise DfdInputError(f"skeleton encoder: heads and tails must be (S, 3) with S >= 1, got {H.shape} and "
                                f"{T.shape}; build them with dfd.encoders.bone_segments(positions, parents)")
        if not (np.isfinite(H).all() and np.isfinite(T).all()):
            raise DfdInputError("skeleton encoder: bone segments contain NaN or infinity")
        if nearest < 1:
            raise DfdInputError(f"skeleton encoder: nearest must be >= 1, got {nearest}")
        self.heads, self.tails = H, T
        self.nearest = int(min(nearest, len(H)))
        self.describe = bool(describe)
        self.chunk = int(chunk)
        self.channels = self.CHANNELS if self.describe else self.CHANNELS - 7
        self.feature_dim = self.channels * self.nearest
        ends = np.vstack([H, T])
        lo, hi = ends.min(axis=0), ends.max(axis=0)
        self.extent = max(float(np.linalg.norm(hi - lo)), 1e-12)
        U = T - H
        self.lengths = np.linalg.norm(U, axis=1)
        self.directions = U / np.maximum(self.lengths, 1e-12)[:, None]
        # frame axis: the world axis least aligned with the bone, made orthogonal to it
        ref = np.eye(3)[np.argmin(np.abs(self.directions), axis=1)]
        e1 = ref - (ref * self.directions).sum(axis=1, keepdims=True) * self.directions
        self.e1 = e1 / np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-12)
        self.e2 = np.cross(self.directions, self.e1)
        centre = 0.5 * (lo + hi)
        self.descriptors = np.hstack([
            (self.lengths / self.extent)[:, None],
            np.abs(self.directions),
            np.abs(0.5 * (H + T) - centre) / self.extent,
        ])

    def settings(self) -> dict:
        """Everything that changes the features (stored with distilled fields)."""
        h = hashlib.sha256(np.ascontiguousarray(self.heads).tobytes() + np.ascontiguousarray(self.tails).tobytes())
        return {"name": self.name, "nearest": self.nearest, "describe": self.describe, "bones": len(self.heads),
                "segments": h.hexdigest()[:16]}

    def point_features(self, X):
        """Unstandardized channels ``(q, feature_dim)`` float64 of points ``X`` ``(q, 3)``."""
        X = np.asarray(X, dtype=np.float64)
        out = np.empty((len(X), self.feature_dim))
        L2 = np.maximum(self.lengths**2, 1e-24)
        for a in range(0, len(X), self.chunk):
            x = X[a : a + self.chunk]
            rel = x[:, None, :] - self.heads[None]  # (q, S, 3)
            t = np.einsum("qsk,sk->qs", rel, self.tails - self.heads) / L2
            foot = self.heads[None] + np.clip(t, 0.0, 1.0)[..., None] * (self.tails - self.heads)[None]
            d = np.linalg.norm(x[:, None, :] - foot, axis=2)
            rows = np.arange(len(x))[:, None]
            s = d.argpartition(self.nearest - 1, axis=1)[:, : self.nearest] if self.nearest < d.shape[1] \
                else np.broadcast_to(np.arange(d.shape[1]), d.shape)
            s = np.take_along_axis(s, np.argsort(d[rows, s], axis=1), axis=1)  # (q, K) bone of each rank
            ts, ds = t[rows, s], d[rows, s]
            radial = rel[rows, s] - ts[..., None] * (self.tails - self.heads)[s]
            r = np.linalg.norm(radial, axis=2)
            cos = np.einsum("qkc,qkc->qk", radial, self.e1[s]) / np.maximum(r, 1e-12)
            sin = np.einsum("qkc,qkc->qk", radial, self.e2[s]) / np.maximum(r, 1e-12)
            L = self.lengths[s]
            block = np.concatenate([
                np.clip(ts, -0.5, 1.5)[..., None],
                (ds / np.maximum(ds + L, 1e-12))[..., None],
                (ds / self.extent)[..., None],
                cos[..., None],
                np.abs(sin)[..., None],
            ] + ([self.descriptors[s]] if self.describe else []), axis=2)
            out[a : a + self.chunk] = block.reshape(len(x), -1)
        return out

    @property
    def channel_groups(self):
        """``(start, stop, weight)`` of each described bone's channels (rank ``r`` weighs ``1 / (r + 1)``)."""
        c = self.channels
        return [(r * c, (r + 1) * c, 1.0 / (r + 1)) for r in range(self.nearest)]


class HeatKernelEncoder(PointEncoder):
    """Heat kernel signature (Sun et al. 2009) of the surface point of each pixel.

    ``HKS(x, t) = sum_i exp(-lambda_i t) phi_i(x)^2`` over the first ``eigenpairs`` eigenpairs of the
    cotangent Laplacian ``L phi = lambda M phi`` (lumped Voronoi mass) of the mesh welded by
    position, at ``times`` log-spaced from ``4 ln 10 / lambda_max`` to ``4 ln 10 / lambda_min``
    (the smallest non-zero eigenvalue), each divided by its mean over the vertices (scale
    invariant), then ``log``. Intrinsic: unchanged by bending and by a mirror image, the same on
    parts of the same shape. A pixel's value is interpolated at its closest point on the mesh.
    Channels are standardized over the covered pixels, rows L2-normalized.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        The mesh (split or welded); the rendered mesh may be its decimation.
    eigenpairs : int
    times : int
        Number of time scales (the feature size).
    """

    name = "hks"

    def __init__(self, V, F, *, eigenpairs=32, times=8):
        from dfd.mesh import check_mesh, weld

        V, F = check_mesh(V, F, stage="hks encoder")
        Vw, _, Fw = weld(V, F)
        keep = (Fw[:, 0] != Fw[:, 1]) & (Fw[:, 1] != Fw[:, 2]) & (Fw[:, 0] != Fw[:, 2])
        self.V, self.F = Vw, np.ascontiguousarray(Fw[keep])
        self.eigenpairs = int(min(eigenpairs, len(Vw) - 2))
        if self.eigenpairs < 2:
            raise DfdInputError(f"hks encoder: the mesh has {len(Vw)} welded vertices; at least 4 are needed")
        self.feature_dim = int(times)
        self.vertex_hks = self._signature()

    def _signature(self):
        import igl
        import scipy.sparse as sp
        from scipy.sparse.linalg import eigsh

        L = -igl.cotmatrix(self.V, self.F)
        L.data = np.nan_to_num(L.data)
        M = igl.massmatrix(self.V, self.F, igl.MASSMATRIX_TYPE_VORONOI)
        m = np.asarray(M.diagonal(), dtype=np.float64)
        m = np.maximum(np.nan_to_num(m), 1e-2 * max(float(np.nanmean(m)), 1e-300))
        M = sp.diags(m)
        # shift-invert just below zero: L + eps M is positive definite on every component; eps
        # relative to the Laplacian's scale (an absolute shift vanishes against large cotangents,
        # leaving a numerically singular factor on the corpus's Adventurer)
        eps = 1e-6 * float(np.abs(L.diagonal()).mean()) / float(m.mean())
        vals, vecs = eigsh(L.tocsc(), k=self.eigenpairs, M=M.tocsc(), sigma=-eps, which="LM")
        vals = np.maximum(vals, 0.0)
        positive = vals[vals > 1e-8 * max(float(vals.max()), 1e-300)]
        lo = float(positive.min()) if len(positive) else 1.0
        hi = float(vals.max()) if vals.max() > 0 else 1.0
        ts = np.geomspace(4 * np.log(10) / hi, 4 * np.log(10) / lo, self.feature_dim)
        H = (vecs**2) @ np.exp(-np.outer(vals, ts))  # (n, times)
        H /= np.maximum(H.mean(axis=0, keepdims=True), 1e-300)
        return np.log(np.maximum(H, 1e-12))

    def settings(self) -> dict:
        """Everything that changes the features (stored with distilled fields)."""
        h = hashlib.sha256(np.ascontiguousarray(self.V).tobytes() + np.ascontiguousarray(self.F).tobytes())
        return {"name": self.name, "eigenpairs": self.eigenpairs, "times": self.feature_dim,
                "mesh": h.hexdigest()[:16]}

    def point_features(self, X):
        """Unstandardized log-HKS ``(q, times)`` at points ``X`` ``(q, 3)`` (closest mesh point)."""
        import igl

        X = np.ascontiguousarray(X, dtype=np.float64)
        _, face, closest = igl.point_mesh_squared_distance(X, self.V, self.F)
        corners = self.V[self.F[face]]
        bary = np.asarray(igl.barycentric_coordinates(
            *(np.ascontiguousarray(a) for a in (closest, corners[:, 0], corners[:, 1], corners[:, 2]))))
        bary = np.clip(np.nan_to_num(bary), 0.0, 1.0)
        bary /= np.maximum(bary.sum(axis=1, keepdims=True), 1e-12)
        return np.einsum("qk,qkc->qc", bary, self.vertex_hks[self.F[face]])

    @property
    def channel_groups(self):
        """``(start, stop, weight)``: one group of every time scale."""
        return [(0, self.feature_dim, 1.0)]


class CombinedEncoder:
    """Several encoders side by side: their unit features, each scaled by the square root of its
    weight (its share of the squared norm), concatenated and L2-normalized.

    Parameters
    ----------
    encoders : sequence of Encoder
    weights : sequence of float, optional
        Relative weights (default equal).
    """

    def __init__(self, encoders, weights=None):
        self.encoders = list(encoders)
        if not self.encoders:
            raise DfdInputError("combined encoder: needs at least one encoder")
        w = np.ones(len(self.encoders)) if weights is None else np.asarray(weights, dtype=np.float64)
        if w.shape != (len(self.encoders),) or (w < 0).any() or w.sum() <= 0:
            raise DfdInputError(f"combined encoder: one non-negative weight per encoder, got {weights}")
        self.weights = w / w.sum()
        self.feature_dim = int(sum(e.feature_dim for e in self.encoders))
        self.name = "+".join(getattr(e, "name", type(e).__name__) for e in self.encoders)

    def settings(self) -> dict:
        """Everything that changes the features (stored with distilled fields)."""
        parts = [e.settings() if hasattr(e, "settings") else {"name": type(e).__name__} for e in self.encoders]
        return {"name": "combined", "encoders": parts, "weights": [float(x) for x in self.weights]}

    def encode(self, images):
        """Features of images alone (each encoder's ``encode``)."""
        return _unit(np.concatenate([e.encode(images) * np.sqrt(w) for e, w in zip(self.encoders, self.weights)],
                                    axis=-1))

    def encode_views(self, views):
        """Features of rendered views (each encoder's :func:`encode_views`)."""
        return _unit(np.concatenate([encode_views(e, views) * np.sqrt(w) for e, w in zip(self.encoders, self.weights)],
                                    axis=-1))


def point_field(encoder, reference):
    """A feature field without distillation, for an encoder whose features are a function of the
    surface point (``point_features`` and ``channel_groups``: :class:`SkeletonEncoder`,
    :class:`HeatKernelEncoder`).

    Parameters
    ----------
    encoder : SkeletonEncoder or HeatKernelEncoder
    reference : (n, 3) float array
        Points that standardize the channels (the mesh's vertices), as the covered pixels do in
        ``encode_views``.

    Returns
    -------
    callable
        ``field(points (q, 3)) -> (q, feature_dim)`` float32 unit features.
    """
    if not (hasattr(encoder, "point_features") and hasattr(encoder, "channel_groups")):
        raise DfdInputError(f"point_field: {type(encoder).__name__} has no point_features; distill a field instead")
    ref = encoder.point_features(np.asarray(reference, dtype=np.float64))
    mean, std = ref.mean(axis=0), ref.std(axis=0)
    std = np.where(std > 1e-8, std, 1.0)
    groups = encoder.channel_groups

    def field(points):
        X = (encoder.point_features(np.asarray(points, dtype=np.float64)) - mean) / std
        for a, b, w in groups:
            X[:, a:b] *= w / np.sqrt(b - a)
        return _unit(X)

    return field


#: Registered encoder names.
ENCODERS = ("filterbank", "skeleton", "hks", "dinov2")


def get_encoder(name="filterbank", **kwargs):
    """An encoder by name.

    Parameters
    ----------
    name : {"filterbank", "skeleton", "hks", "dinov2"}
    **kwargs
        Passed to the encoder's constructor (``heads=``, ``tails=`` for ``"skeleton"``; ``V=``,
        ``F=`` for ``"hks"``; ``checkpoint=`` for ``"dinov2"``).

    Returns
    -------
    Encoder
    """
    if name == "filterbank":
        return FilterBankEncoder(**kwargs)
    if name == "skeleton":
        return SkeletonEncoder(**kwargs)
    if name == "hks":
        return HeatKernelEncoder(**kwargs)
    if name == "dinov2":
        from dfd.dinov2 import DinoV2Encoder

        return DinoV2Encoder(**kwargs)
    raise DfdInputError(f"encoder: unknown encoder {name!r}; expected one of {', '.join(ENCODERS)}")


def __getattr__(name):
    # DinoV2Encoder lives in dfd.dinov2 (it needs torch); import it only when asked for
    if name == "DinoV2Encoder":
        from dfd.dinov2 import DinoV2Encoder

        return DinoV2Encoder
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
