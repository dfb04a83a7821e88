"""DINOv2 ViT encoder in plain torch, loading the official checkpoints from a local file.

The architecture follows facebookresearch/dinov2 ``dinov2/models/vision_transformer.py``
(patch embedding by a stride-14 convolution, class token, learned position embedding
interpolated bicubically to the input size, optional register tokens, pre-norm blocks with
LayerScale, final LayerNorm) and keeps its parameter names, so the released state dicts
(``dinov2_vits14_pretrain.pth``, ``dinov2_vitb14_pretrain.pth``, and the ``_reg4`` variants)
load as they are: ``patch_embed.proj.weight``, ``cls_token``, ``pos_embed``, ``mask_token``,
``blocks.0.norm1.weight``, ``blocks.0.attn.qkv.weight``, ``blocks.0.attn.proj.weight``,
``blocks.0.ls1.gamma``, ``blocks.0.mlp.fc1.weight``, ``blocks.0.ls2.gamma``, ``norm.weight``...
It is implemented here rather than through ``timm`` because ``timm`` needs ``torchvision``,
which does not import beside the CPU torch build this project pins.

dfd never downloads weights: the checkpoint is a path given to :class:`DinoV2Encoder`, or the
environment variable ``DFD_DINOV2_CHECKPOINT``, or ``~/.cache/dfd/dinov2_vits14_pretrain.pth``.
"""

from __future__ import annotations

import logging
import math
import os
import re
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as TF
from torch import nn

from dfd.errors import DfdInputError, MissingCheckpointError

__all__ = ["DinoVisionTransformer", "DinoV2Encoder", "load_dinov2", "DEFAULT_CHECKPOINT", "ENV_CHECKPOINT"]

log = logging.getLogger(__name__)

ENV_CHECKPOINT = "DFD_DINOV2_CHECKPOINT"
DEFAULT_CHECKPOINT = (
    Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "dfd" / "dinov2_vits14_pretrain.pth"
)
#: Heads of the released models by embedding width (ViT-S, B, L, g); others use width // 64.
HEADS_BY_WIDTH = {384: 6, 768: 12, 1024: 16, 1536: 24}
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class PatchEmbed(nn.Module):
    """Image ``(B, 3, H, W)`` -> patch tokens ``(B, H/p * W/p, D)`` by a stride-``p`` convolution."""

    def __init__(self, patch_size=14, in_chans=3, embed_dim=384):
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(in_chans, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x):
        return self.proj(x).flatten(2).transpose(1, 2)


class Attention(nn.Module):
    def __init__(self, dim, num_heads, qkv_bias=True, proj_bias=True):
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, dim * 3, bias=qkv_bias)
        self.proj = nn.Linear(dim, dim, bias=proj_bias)

    def forward(self, x):
        B, N, C = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, C // self.num_heads).permute(2, 0, 3, 1, 4)
        x = TF.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2])
        return self.proj(x.transpose(1, 2).reshape(B, N, C))


class Mlp(nn.Module):
    def __init__(self, dim, hidden, bias=True):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden, bias=bias)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim, bias=bias)

    def forward(self, x):
        return self.fc2(self.act(self.fc1(x)))


class LayerScale(nn.Module):
    def __init__(self, dim, init_values=1e-5):
        super().__init__()
        self.gamma = nn.Parameter(init_values * torch.ones(dim))

    def forward(self, x):
        return x * self.gamma


class Block(nn.Module):
    """Pre-norm transformer block with LayerScale: ``x + ls1(attn(norm1 x))``, ``+ ls2(mlp(norm2 x))``."""

    def __init__(self, dim, num_heads, mlp_hidden, *, qkv_bias=True, layerscale=True):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, num_heads, qkv_bias=qkv_bias)
        self.ls1 = LayerScale(dim) if layerscale else nn.Identity()
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, mlp_hidden)
        self.ls2 = LayerScale(dim) if layerscale else nn.Identity()

    def forward(self, x):
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class DinoVisionTransformer(nn.Module):
    """The DINOv2 backbone (no head).

    Parameters
    ----------
    img_size : int
        Training image size of the position embedding (518 for the released models: 37 x 37
        patches); other sizes are handled by interpolating it.
    patch_size, embed_dim, depth, num_heads : int
    mlp_ratio : float
    num_register_tokens : int
        4 for the ``_reg4`` models, else 0.
    qkv_bias, layerscale : bool
    """

    def __init__(
        self,
        *,
        img_size=518,
        patch_size=14,
        embed_dim=384,
        depth=12,
        num_heads=6,
        mlp_ratio=4.0,
        num_register_tokens=0,
        qkv_bias=True,
        layerscale=True,
    ):
        super().__init__()
        self.patch_size = patch_size
        self.embed_dim = embed_dim
        self.num_register_tokens = num_register_tokens
        n_patches = (img_size // patch_size) ** 2
        self.patch_embed = PatchEmbed(patch_size, 3, embed_dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, n_patches + 1, embed_dim))
        if num_register_tokens:
            self.register_tokens = nn.Parameter(torch.zeros(1, num_register_tokens, embed_dim))
        self.mask_token = nn.Parameter(torch.zeros(1, embed_dim))
        hidden = int(embed_dim * mlp_ratio)
        self.blocks = nn.ModuleList(
            [Block(embed_dim, num_heads, hidden, qkv_bias=qkv_bias, layerscale=layerscale) for _ in range(depth)]
        )
        self.norm = nn.LayerNorm(embed_dim, eps=1e-6)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)

    def interpolate_pos_encoding(self, h_patches, w_patches):
        """Position embedding ``(1, 1 + h*w, D)`` for a ``h x w`` patch grid (bicubic)."""
        pos = self.pos_embed
        n = pos.shape[1] - 1
        if n == h_patches * w_patches and h_patches == w_patches:
            return pos
        m = int(math.sqrt(n))
        grid = pos[:, 1:].reshape(1, m, m, -1).permute(0, 3, 1, 2)
        grid = TF.interpolate(grid.float(), size=(h_patches, w_patches), mode="bicubic", antialias=False)
        grid = grid.to(pos.dtype).permute(0, 2, 3, 1).reshape(1, h_patches * w_patches, -1)
        return torch.cat([pos[:, :1], grid], dim=1)

    def forward_patch_tokens(self, x):
        """Normalized patch tokens.

        Parameters
        ----------
        x : (B, 3, H, W) tensor
            ImageNet-normalized images, ``H`` and ``W`` multiples of the patch size.

        Returns
        -------
        (B, H/p, W/p, D) tensor
        """
        B, _, H, W = x.shape
        h, w = H // self.patch_size, W // self.patch_size
        x = self.patch_embed(x)
        x = torch.cat([self.cls_token.expand(B, -1, -1), x], dim=1)
        x = x + self.interpolate_pos_encoding(h, w)
        if self.num_register_tokens:
            x = torch.cat([x[:, :1], self.register_tokens.expand(B, -1, -1), x[:, 1:]], dim=1)
        for block in self.blocks:
            x = block(x)
        x = self.norm(x)
        return x[:, 1 + self.num_register_tokens :].reshape(B, h, w, -1)


def _clean_state_dict(state):
    """Unwrap training checkpoints (``teacher``/``model``) and strip ``backbone.``/``module.``."""
    for key in ("teacher", "model", "state_dict"):
        if isinstance(state, dict) and key in state and isinstance(state[key], dict):
            state = state[key]
    out = {}
    for k, v in state.items():
        for prefix in ("module.", "backbone."):
            if k.startswith(prefix):
                k = k[len(prefix) :]
        if k.startswith("dino_head") or k.startswith("ibot_head") or k.startswith("head."):
            continue
        out[k] = v
    return out


def load_dinov2(path, *, num_heads=None) -> DinoVisionTransformer:
    """Build the ViT that a DINOv2 state dict describes and load it.

    Parameters
    ----------
    path : str or Path
        A ``.pth``/``.pt`` file holding the state dict with the official key names.
    num_heads : int, optional
        Attention heads; the state dict does not record them. Default: 6 / 12 / 16 / 24 for the
        released widths 384 / 768 / 1024 / 1536, else ``max(1, width // 64)``.

    Returns
    -------
    DinoVisionTransformer
        In eval mode, on the CPU.
    """
    path = Path(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a truncated or foreign file: say which
        raise DfdInputError(f"dinov2: cannot read checkpoint {path}: {exc}") from exc
    state = _clean_state_dict(state)
    required = ("patch_embed.proj.weight", "cls_token", "pos_embed", "norm.weight")
    missing = [k for k in required if k not in state]
    if missing:
        raise DfdInputError(
            f"dinov2: {path} is not a DINOv2 ViT state dict (missing {', '.join(missing)}); "
            "expected the official dinov2_vit{s,b}14 weights"
        )
    if any(".mlp.w12." in k for k in state):
        raise DfdInputError(f"dinov2: {path} uses the SwiGLU feed-forward of ViT-g, which dfd does not implement")
    if any(re.match(r"blocks\.\d+\.\d+\.", k) for k in state):
        raise DfdInputError(f"dinov2: {path} stores chunked blocks (blocks.i.j.*); save it with unchunked blocks")
    width = state["cls_token"].shape[-1]
    patch = state["patch_embed.proj.weight"].shape[-1]
    depth = 1 + max(int(m.group(1)) for k in state if (m := re.match(r"blocks\.(\d+)\.", k)))
    hidden = state["blocks.0.mlp.fc1.weight"].shape[0]
    n_pos = state["pos_embed"].shape[1] - 1
    grid = int(round(math.sqrt(n_pos)))
    model = DinoVisionTransformer(
        img_size=grid * patch,
        patch_size=patch,
        embed_dim=width,
        depth=depth,
        num_heads=num_heads or HEADS_BY_WIDTH.get(width, max(1, width // 64)),
        mlp_ratio=hidden / width,
        num_register_tokens=state["register_tokens"].shape[1] if "register_tokens" in state else 0,
        qkv_bias="blocks.0.attn.qkv.bias" in state,
        layerscale="blocks.0.ls1.gamma" in state,
    )
    state.setdefault("mask_token", model.mask_token.detach().clone())
    result = model.load_state_dict(state, strict=False)
    if result.missing_keys or result.unexpected_keys:
        raise DfdInputError(
            f"dinov2: {path} does not match the DINOv2 architecture: missing {result.missing_keys[:5]}, "
            f"unexpected {result.unexpected_keys[:5]}"
        )
    log.debug("dinov2: loaded %s (width %d, depth %d, patch %d)", path, width, depth, patch)
    return model.eval()


def _resolve_checkpoint(checkpoint):
    if checkpoint is None:
        checkpoint = os.environ.get(ENV_CHECKPOINT) or DEFAULT_CHECKPOINT
    checkpoint = Path(checkpoint).expanduser()
    if not checkpoint.is_file():
        raise MissingCheckpointError(
            f"dinov2: no checkpoint at {checkpoint}. dfd never downloads weights: save the official "
            f"DINOv2 state dict (e.g. dinov2_vits14_pretrain.pth from github.com/facebookresearch/dinov2) "
            f"at {DEFAULT_CHECKPOINT}, or pass its path (checkpoint=..., --checkpoint) or set "
            f"{ENV_CHECKPOINT}=/path/to/file.pth; or use the 'filterbank' encoder, which needs no weights"
        )
    return checkpoint


class DinoV2Encoder:
    """DINOv2 patch tokens, upsampled bilinearly to every pixel and L2-normalized.

    Parameters
    ----------
    checkpoint : str or Path, optional
        State dict file; default ``$DFD_DINOV2_CHECKPOINT``, else
        ``~/.cache/dfd/dinov2_vits14_pretrain.pth``. A missing file raises
        :class:`dfd.errors.MissingCheckpointError` saying where to put it.
    num_heads : int, optional
        See :func:`load_dinov2`.
    image_size : int, optional
        Side of the (square) network input; images are resized to it. Default: the image size
        rounded to a multiple of the patch size.
    batch_size : int
        Images per forward pass.
    """

    name = "dinov2"

    def __init__(self, checkpoint=None, *, num_heads=None, image_size=None, batch_size=8):
        self.checkpoint = _resolve_checkpoint(checkpoint)
        self.model = load_dinov2(self.checkpoint, num_heads=num_heads)
        self.feature_dim = self.model.embed_dim
        self.image_size = image_size
        self.batch_size = int(batch_size)

    def settings(self) -> dict:
        """Everything that changes the features (stored with distilled fields)."""
        return {
            "name": self.name,
            "checkpoint": self.checkpoint.name,
            "checkpoint_bytes": self.checkpoint.stat().st_size,
            "image_size": self.image_size,
        }

    def encode(self, images):
        """Per-pixel DINOv2 features.

        Parameters
        ----------
        images : (B, H, W, 3) float array in [0, 1]

        Returns
        -------
        (B, H, W, feature_dim) float32, unit rows.
        """
        images = np.asarray(images, dtype=np.float32)
        if images.ndim != 4 or images.shape[-1] != 3:
            raise DfdInputError(f"dinov2: images must be (B, H, W, 3), got shape {images.shape}")
        B, H, W, _ = images.shape
        p = self.model.patch_size
        side = self.image_size or max(p, int(round(max(H, W) / p)) * p)
        mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
        out = np.empty((B, H, W, self.feature_dim), dtype=np.float32)
        with torch.inference_mode():
            for start in range(0, B, self.batch_size):
                x = torch.from_numpy(images[start : start + self.batch_size]).permute(0, 3, 1, 2)
                if (H, W) != (side, side):
                    x = TF.interpolate(x, size=(side, side), mode="bilinear", align_corners=False)
                tokens = self.model.forward_patch_tokens((x - mean) / std).permute(0, 3, 1, 2)
                f = TF.interpolate(tokens, size=(H, W), mode="bilinear", align_corners=False)
                f = TF.normalize(f, dim=1).permute(0, 2, 3, 1)
                out[start : start + len(x)] = f.numpy()
        return out

    def encode_views(self, views):
        """Features of the shaded renders (DINOv2 sees colour only)."""
        return self.encode(views.rgb)
