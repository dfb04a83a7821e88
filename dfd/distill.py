"""Barycentric feature distillation: train a feature field on every covered pixel of the views
(PIPELINE.md section 6).

Each covered pixel gives a 3D surface point (its triangle and barycentric coordinates) and an
encoder feature; the field regresses the features at the points (squared error, Adam, learning
rate 1e-3). The cost depends on the number of pixels, not on the mesh: meshes above the face
budget are decimated (quadric error metrics, ``fast-simplification``) before rendering, and the
field is then evaluated on the full mesh.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from dfd.encoders import encode_views, get_encoder
from dfd.errors import DfdInputError
from dfd.field import FeatureField, load_field
from dfd.mesh import check_mesh, mesh_hash, normalization, weld
from dfd.render import render_views, surface_points

__all__ = ["distill", "decimate", "training_samples", "Adam", "cosine_rates", "DEFAULT_STEPS", "DEFAULT_BATCH_SIZE"]

log = logging.getLogger(__name__)

#: Adam steps and samples per step: about 2-3 passes over the ~400k covered pixels of 24 views
#: at 224 px, within the 60 s budget of a 50k-face mesh on 2 CPU cores (benchmarks/dfd_bench.py).
DEFAULT_STEPS = 300
DEFAULT_BATCH_SIZE = 4096


class Adam:
    """Adam as ``torch.optim.Adam`` computes it on CPU tensors (its single-tensor update: betas
    0.9 and 0.999, eps 1e-8, no weight decay), the same operations in the same order, so the
    fields are bit for bit those torch's optimizer trains.

    Written out because every ``torch.optim`` optimizer imports the compiler stack
    (``torch._dynamo``, about 2 s) on its first ``add_param_group``, in each process that
    distills a field, before any training step."""

    def __init__(self, params, betas=(0.9, 0.999), eps=1e-8):
        self.params = list(params)
        self.beta1, self.beta2 = betas
        self.eps = eps
        self.exp_avg = [torch.zeros_like(p) for p in self.params]
        self.exp_avg_sq = [torch.zeros_like(p) for p in self.params]
        # per parameter, as torch counts them (its float32 count is exact below 2**24 steps)
        self.steps = [0] * len(self.params)

    def zero_grad(self):
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self, lr):
        """One update at learning rate ``lr`` of every parameter that has a gradient."""
        for i, (p, m, v) in enumerate(zip(self.params, self.exp_avg, self.exp_avg_sq)):
            if p.grad is None:
                continue
            g = p.grad
            self.steps[i] += 1
            m.lerp_(g, 1 - self.beta1)
            v.mul_(self.beta2).addcmul_(g, g, value=1 - self.beta2)
            bias_correction1 = 1 - self.beta1 ** self.steps[i]
            bias_correction2 = 1 - self.beta2 ** self.steps[i]
            denom = (v.sqrt() / bias_correction2**0.5).add_(self.eps)
            p.addcdiv_(m, denom, value=-(lr / bias_correction1))


def cosine_rates(lr, steps):
    """The learning rate of each of ``steps`` steps under ``torch.optim.lr_scheduler.
    CosineAnnealingLR(T_max=max(steps, 1), eta_min=0)``, by the recursive form torch uses
    (each rate from the last), so that the rounding is torch's too."""
    period = max(steps, 1)
    rate = float(lr)
    for step in range(steps):
        yield rate
        rate = (1 + math.cos(math.pi * (step + 1) / period)) / (1 + math.cos(math.pi * step / period)) * rate


def decimate(V, F, face_budget, *, vertex_colors=None, uvs=None):
    """Quadric simplification to at most about ``face_budget`` triangles.

    The mesh is welded by position first (glTF meshes are split at every seam, and a split mesh
    would tear open). Vertex colours and UVs move to the decimated vertices by closest point on
    the input surface (a decimated triangle that spans a UV seam gets interpolated UVs across it).

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    face_budget : int
    vertex_colors : (n, c) float array, optional
    uvs : (n, 2) float array, optional

    Returns
    -------
    Vd : (k, 3) float64
    Fd : (l, 3) int64
        ``l <= m``; the input itself (copied) when ``m <= face_budget``.
    colors : (k, c) float64 or None
    uvs : (k, 2) float64 or None
    """
    V, F = check_mesh(V, F, stage="distill")
    if len(F) <= face_budget:
        return V.copy(), F.copy(), vertex_colors, uvs
    import fast_simplification
    import igl

    Vw, _, Fw = weld(V, F)
    Vd, Fd = fast_simplification.simplify(Vw, Fw.astype(np.int32), target_reduction=1.0 - face_budget / len(F))
    Vd = np.asarray(Vd, dtype=np.float64)
    Fd = np.asarray(Fd, dtype=np.int64)
    log.debug("distill: decimated %d -> %d faces", len(F), len(Fd))
    if vertex_colors is None and uvs is None:
        return Vd, Fd, None, None
    _, face, closest = igl.point_mesh_squared_distance(Vd, V, F.astype(np.int64))
    corners = V[F[face]]  # (k, 3, 3)
    points = (closest, corners[:, 0], corners[:, 1], corners[:, 2])
    bary = np.asarray(igl.barycentric_coordinates(*(np.ascontiguousarray(a) for a in points)))
    bary = np.clip(bary, 0.0, 1.0)
    bary /= np.maximum(bary.sum(axis=1, keepdims=True), 1e-12)

    def carry(A):
        if A is None:
            return None
        A = np.asarray(A, dtype=np.float64)
        return np.einsum("nk,nkj->nj", bary, A[F[face]])

    return Vd, Fd, carry(vertex_colors), carry(uvs)


def training_samples(V, F, views, features):
    """Points and target features of every covered pixel.

    Parameters
    ----------
    V : (n, 3) float array
        The rendered mesh.
    F : (m, 3) int array
    views : dfd.render.Views
    features : (B, H, W, C) float array
        Encoder features of the views.

    Returns
    -------
    points : (k, 3) float64
        Surface points in mesh coordinates.
    targets : (k, C) float32
    """
    points = surface_points(V, F, views)
    targets = np.asarray(features, dtype=np.float32)[views.mask]
    return points, targets


def _seeded(seed):
    """Seed torch's global generator (network initialization) and return a generator for the
    sampling. The CPU kernels used here (linear layers, LayerNorm, Adam, indexing) are
    deterministic for a given thread count (:func:`_one_thread` fixes it), so this is enough
    for identical fields; we do not call ``torch.use_deterministic_algorithms``, whose first
    call imports the compiler stack (seconds) and changes a process-wide setting."""
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)


@contextmanager
def _one_thread():
    """Train on one torch intra-op thread, whatever ``OMP_NUM_THREADS`` or the core count.

    The backward pass's reductions over the batch split their work by the thread count and
    round differently (the same seed gave other weights with 1 and 2 threads), so a field, and
    the junction weights it judges, would depend on the machine. One thread costs little: the
    network is small, and on two cores two threads were not faster."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _appearance_hash(vertex_colors, uvs, texture):
    h = hashlib.sha256()
    for a in (vertex_colors, uvs, texture):
        h.update(b"-" if a is None else np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def distill(
    V,
    F,
    *,
    encoder="filterbank",
    n_views=24,
    resolution=224,
    layout="prototype",
    face_budget=50_000,
    steps=DEFAULT_STEPS,
    batch_size=DEFAULT_BATCH_SIZE,
    lr=1e-3,
    lr_decay=True,
    n_frequencies=0,
    seed=0,
    vertex_colors=None,
    uvs=None,
    texture=None,
    cache=None,
    encoder_kwargs=None,
    progress=None,
) -> FeatureField:
    """Distill a feature field for a mesh from encoder features of its renders.

    Parameters
    ----------
    V : (n, 3) float array
        Vertex positions, any units.
    F : (m, 3) int array
    encoder : str or Encoder
        ``"filterbank"`` (default, no weights), ``"dinov2"``, or an encoder object.
    n_views, resolution, layout
        Views, see :func:`dfd.render.render_views`.
    face_budget : int
        Meshes with more triangles are decimated to this count before rendering.
    steps : int
        Adam steps.
    batch_size : int
        Pixels per step, drawn at random (seeded) from all covered pixels.
    lr : float
        Adam learning rate.
    lr_decay : bool
        Anneal the learning rate to 0 over the steps (cosine). Our addition: it removes most of
        the stochastic-gradient noise that the last steps leave in the field, which otherwise
        shows as spurious asymmetry (measured: mean mirror feature distance 0.165 without it on
        a mirror-symmetric figure).
    n_frequencies : int
        Fourier feature octaves of the field (0: raw coordinates).
    seed : int
        Seeds the network initialization and the sampling; with deterministic kernels, the same
        inputs and settings give the same field.
    vertex_colors, uvs, texture : arrays, optional
        Appearance, see :func:`dfd.render.render_views`.
    cache : str or Path, optional
        Folder of distilled fields; a field with the same mesh hash and settings is loaded
        instead of trained, and a new one is saved there.
    encoder_kwargs : dict, optional
        Passed to :func:`dfd.encoders.get_encoder` when ``encoder`` is a name.
    progress : callable, optional
        ``progress(step, steps)`` after each step.

    Returns
    -------
    FeatureField
        In eval mode; evaluate it on the full mesh with ``field.evaluate(V)``.
    """
    V, F = check_mesh(V, F, stage="distill")
    if steps < 0 or batch_size < 1:
        raise DfdInputError(f"distill: steps must be >= 0 and batch_size >= 1, got {steps} and {batch_size}")
    enc = get_encoder(encoder, **(encoder_kwargs or {})) if isinstance(encoder, str) else encoder
    enc_settings = enc.settings() if hasattr(enc, "settings") else {"name": type(enc).__name__}
    settings = {
        "encoder": enc_settings,
        "feature_dim": int(enc.feature_dim),
        "n_views": int(n_views),
        "resolution": int(resolution),
        "layout": layout,
        "face_budget": int(face_budget),
        "steps": int(steps),
        "batch_size": int(batch_size),
        "lr": float(lr),
        "lr_decay": bool(lr_decay),
        "n_frequencies": int(n_frequencies),
        "seed": int(seed),
        "appearance": _appearance_hash(vertex_colors, uvs, texture),
    }
    digest = mesh_hash(V, F)
    cache_path = None
    if cache is not None:
        key = hashlib.sha256((digest + json.dumps(settings, sort_keys=True)).encode()).hexdigest()[:24]
        cache_path = Path(cache) / f"field-{key}.pt"
        if cache_path.is_file():
            field = load_field(cache_path)
            if field.mesh_hash == digest and field.settings == settings:
                log.debug("distill: reusing %s", cache_path)
                return field

    Vd, Fd, colors_d, uvs_d = decimate(V, F, face_budget, vertex_colors=vertex_colors, uvs=uvs)
    views = render_views(
        Vd, Fd, vertex_colors=colors_d, uvs=uvs_d, texture=texture,
        n_views=n_views, resolution=resolution, layout=layout,
    )
    features = encode_views(enc, views)
    points, targets = training_samples(Vd, Fd, views, features)
    if len(points) == 0:
        raise DfdInputError("distill: no pixel of any view covers the mesh; is it degenerate?")
    # the network sees the full mesh's normalized frame, which is also the one it is evaluated in
    norm = normalization(V)
    X = torch.from_numpy(norm.apply(points).astype(np.float32))
    Y = torch.from_numpy(targets)
    log.debug("distill: %d training pixels, %d features", len(X), Y.shape[1])

    generator = _seeded(seed)
    field = FeatureField(
        Y.shape[1], n_frequencies=n_frequencies, normalization=norm, mesh_hash=digest, settings=settings
    )
    field.train()
    optimizer = Adam(field.parameters())
    rates = cosine_rates(lr, steps) if lr_decay else (float(lr) for _ in range(steps))
    with _one_thread():
        for step, rate in enumerate(rates):
            idx = torch.randint(len(X), (min(batch_size, len(X)),), generator=generator)
            loss = (field(X[idx]) - Y[idx]).square().sum(dim=1).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step(rate)
            if progress is not None:
                progress(step + 1, steps)
    log.debug("distill: final loss %.4f", float(loss.detach()) if steps else float("nan"))
    field.eval()
    if cache_path is not None:
        field.save(cache_path)
    return field
