"""The feature field: an MLP from 3D points to unit feature vectors (PIPELINE.md section 6).

``3 -> 256`` (ReLU, LayerNorm), four hidden layers of 256 (ReLU, LayerNorm), linear to the
feature size, unit-normalized output; optionally the input is lifted by Fourier features
``[p, sin(2^k pi p), cos(2^k pi p)]``, ``k < n_frequencies``. The network works in the
normalized frame of the distilled mesh (bounding-box centre at the origin, half-extent 1); the
field stores that normalization, so :meth:`FeatureField.evaluate` takes points in the mesh's own
coordinates. Saved fields (``.pt``) carry the weights, the architecture, the normalization, the
hash of the mesh they were distilled from and the distillation settings.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from torch import nn

from dfd.errors import DfdInputError
from dfd.mesh import Normalization

__all__ = ["FeatureField", "load_field", "FIELD_FORMAT"]

log = logging.getLogger(__name__)

FIELD_FORMAT = "dfd-field/1"


class FeatureField(nn.Module):
    """MLP feature field with LayerNorm and unit-normalized output.

    Parameters
    ----------
    feature_dim : int
        Output size ``C`` (the encoder's feature size).
    hidden : int
        Width of every hidden layer (256).
    n_hidden : int
        Hidden layers after the input layer (4).
    n_frequencies : int
        Fourier feature octaves; 0 feeds the raw coordinates.
    normalization : Normalization, optional
        Mesh coordinates -> network coordinates; identity when omitted.
    mesh_hash : str
        Hash of the mesh the field was distilled from (:func:`dfd.mesh.mesh_hash`).
    settings : dict
        Distillation settings (JSON-like), stored and compared by the cache.
    """

    def __init__(
        self, feature_dim, *, hidden=256, n_hidden=4, n_frequencies=0, normalization=None, mesh_hash="", settings=None
    ):
        super().__init__()
        if feature_dim < 1:
            raise DfdInputError(f"field: feature_dim must be positive, got {feature_dim}")
        self.feature_dim = int(feature_dim)
        self.hidden = int(hidden)
        self.n_hidden = int(n_hidden)
        self.n_frequencies = int(n_frequencies)
        self.normalization = normalization or Normalization(center=np.zeros(3), scale=1.0)
        self.mesh_hash = str(mesh_hash)
        self.settings = dict(settings or {})
        layers = [nn.Linear(3 + 6 * self.n_frequencies, self.hidden), nn.ReLU(), nn.LayerNorm(self.hidden)]
        for _ in range(self.n_hidden):
            layers += [nn.Linear(self.hidden, self.hidden), nn.ReLU(), nn.LayerNorm(self.hidden)]
        layers.append(nn.Linear(self.hidden, self.feature_dim))
        self.mlp = nn.Sequential(*layers)
        self.register_buffer("frequencies", (2.0 ** torch.arange(self.n_frequencies, dtype=torch.float32)) * np.pi)

    def encode_positions(self, x):
        """Network input ``(n, 3 + 6 L)`` of normalized points ``(n, 3)``."""
        if self.n_frequencies == 0:
            return x
        angles = (x[:, :, None] * self.frequencies).reshape(len(x), -1)  # (n, 3 L)
        return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=1)

    def forward(self, x):
        """Unit features ``(n, C)`` of points ``(n, 3)`` given in the normalized frame."""
        return nn.functional.normalize(self.mlp(self.encode_positions(x)), dim=1)

    @torch.no_grad()
    def evaluate(self, points, *, batch_size=65536):
        """Field values at points in the mesh's own coordinates.

        Parameters
        ----------
        points : (n, 3) float array
            Positions in the coordinates of the mesh the field was distilled from (on the
            surface, or near it: handles may sit anywhere in space).
        batch_size : int
            Points per forward pass.

        Returns
        -------
        (n, C) float32
            Unit feature vectors.
        """
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise DfdInputError(f"field: points must be (n, 3), got shape {points.shape}")
        was_training = self.training
        self.eval()
        x = self.normalization.apply(points).astype(np.float32)
        out = np.empty((len(points), self.feature_dim), dtype=np.float32)
        for start in range(0, len(x), batch_size):
            out[start : start + batch_size] = self(torch.from_numpy(x[start : start + batch_size])).numpy()
        self.train(was_training)
        return out

    def config(self) -> dict:
        """Constructor arguments (JSON-like) to rebuild this field."""
        return {
            "feature_dim": self.feature_dim,
            "hidden": self.hidden,
            "n_hidden": self.n_hidden,
            "n_frequencies": self.n_frequencies,
            "center": [float(c) for c in self.normalization.center],
            "scale": float(self.normalization.scale),
            "mesh_hash": self.mesh_hash,
            "settings": self.settings,
        }

    def save(self, path):
        """Write the field to a ``.pt`` file (state dict, architecture, normalization, mesh hash,
        settings); read it back with :func:`load_field`."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        torch.save({"format": FIELD_FORMAT, "config": self.config(), "state_dict": self.state_dict()}, tmp)
        tmp.replace(path)  # a concurrent reader never sees half a file


def load_field(path) -> FeatureField:
    """Read a field written by :meth:`FeatureField.save`.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    FeatureField
        In eval mode.
    """
    path = Path(path)
    if not path.is_file():
        raise DfdInputError(f"field: no field file at {path}; create one with `dfd distill MESH -o {path.name}`")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise DfdInputError(f"field: cannot read {path}: {exc}") from exc
    if not isinstance(data, dict) or data.get("format") != FIELD_FORMAT:
        raise DfdInputError(f"field: {path} is not a dfd field file (expected format {FIELD_FORMAT!r})")
    c = data["config"]
    field = FeatureField(
        c["feature_dim"],
        hidden=c["hidden"],
        n_hidden=c["n_hidden"],
        n_frequencies=c["n_frequencies"],
        normalization=Normalization(center=np.asarray(c["center"], dtype=np.float64), scale=float(c["scale"])),
        mesh_hash=c["mesh_hash"],
        settings=c["settings"],
    )
    field.load_state_dict(data["state_dict"])
    return field.eval()
