"""MS-Transformer (Shavit, Ferens & Keller, ICCV 2021): one APR for several scenes.

Backbone feature maps at two resolutions (stride 16 for position, stride 8 for orientation),
learned 2-D positional encodings, one transformer encoder-decoder per pose component, one
learned query per scene, a scene classifier over the decoded queries and shared regression
heads. The decoded query of the selected scene is the latent the heads (and a PAE) see.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from pae.core.geometry import normalize_pose
from pae.models.backbones import Backbone
from pae.models.base import Latents, PoseRegressor


class Tap(NamedTuple):
    """Where a feature map is read: index into `Backbone.features` and its channel count."""

    index: int
    channels: int


REDUCTION_TAPS: dict[str, tuple[Tap, Tap]] = {
    "efficientnet_b0": (Tap(3, 40), Tap(5, 112)),
    "mobilenet_v2": (Tap(6, 32), Tap(13, 96)),
    "resnet50": (Tap(5, 512), Tap(6, 1024)),
    "small_cnn": (Tap(17, 96), Tap(23, 128)),
}
"""Per backbone: the stride-8 and stride-16 feature maps (EfficientNet-B0: the public code's
reduction_3 and reduction_4 endpoints)."""


class MultiScaleFeatures(nn.Module):
    """The stages of a backbone up to its stride-16 map: images [B, 3, H, W] ->
    (fine [B, C8, H/8, W/8], coarse [B, C16, H/16, W/16])."""

    def __init__(self, backbone: Backbone) -> None:
        super().__init__()
        self.fine, self.coarse = REDUCTION_TAPS[backbone.name]
        self.stages = backbone.features[: self.coarse.index + 1]

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor]:
        fine = images
        out = images
        for index, stage in enumerate(self.stages):
            out = stage(out)
            if index == self.fine.index:
                fine = out
        return fine, out


class LearnedPositionEncoding(nn.Module):
    """Learned 2-D positional encoding: [column embedding, row embedding] per cell, each of
    d/2 dimensions, for maps of up to `max_size` rows and columns."""

    def __init__(self, dim: int, max_size: int = 50) -> None:
        super().__init__()
        if dim % 2:
            raise ValueError(f"MSTransformer: latent_dim must be even, got {dim}")
        self.max_size = max_size
        self.row = nn.Embedding(max_size, dim // 2)
        self.col = nn.Embedding(max_size, dim // 2)
        nn.init.uniform_(self.row.weight)
        nn.init.uniform_(self.col.weight)

    def forward(self, height: int, width: int) -> Tensor:
        """-> [height * width, dim], row-major like a flattened feature map."""
        if max(height, width) > self.max_size:
            raise ValueError(
                f"MSTransformer: feature map {height}x{width} exceeds the positional encoding's "
                f"{self.max_size}x{self.max_size}; use smaller images"
            )
        col = self.col.weight[:width].unsqueeze(0).expand(height, -1, -1)
        row = self.row.weight[:height].unsqueeze(1).expand(-1, width, -1)
        return torch.cat([col, row], dim=-1).flatten(0, 1)


class EncoderLayer(nn.Module):
    """Pre-norm self-attention + GELU feed-forward; the positional encoding is added to the
    queries and keys of every layer."""

    def __init__(self, dim: int, heads: int, feedforward: int, dropout: float) -> None:
        super().__init__()
        self.self_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.norm_attn = nn.LayerNorm(dim)
        self.ff = FeedForward(dim, feedforward, dropout)
        self.drop_attn = nn.Dropout(dropout)

    def forward(self, tokens: Tensor, pos: Tensor) -> Tensor:
        """tokens [B, N, d], pos [N, d] -> [B, N, d]."""
        h = self.norm_attn(tokens)
        qk = h + pos
        tokens = tokens + self.drop_attn(self.self_attn(qk, qk, h, need_weights=False)[0])
        return self.ff(tokens)


class DecoderLayer(nn.Module):
    """Pre-norm self-attention over the scene queries, cross-attention into the encoder's
    memory, GELU feed-forward."""

    def __init__(self, dim: int, heads: int, feedforward: int, dropout: float) -> None:
        super().__init__()
        self.self_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.cross_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.norm_attn = nn.LayerNorm(dim)
        self.norm_cross = nn.LayerNorm(dim)
        self.ff = FeedForward(dim, feedforward, dropout)
        self.drop_attn = nn.Dropout(dropout)
        self.drop_cross = nn.Dropout(dropout)

    def forward(self, target: Tensor, memory: Tensor, pos: Tensor, query_pos: Tensor) -> Tensor:
        """target [B, S, d], memory [B, N, d], pos [N, d], query_pos [S, d] -> [B, S, d]."""
        h = self.norm_attn(target)
        qk = h + query_pos
        target = target + self.drop_attn(self.self_attn(qk, qk, h, need_weights=False)[0])
        h = self.norm_cross(target)
        attended = self.cross_attn(h + query_pos, memory + pos, memory, need_weights=False)[0]
        target = target + self.drop_cross(attended)
        return self.ff(target)


class FeedForward(nn.Module):
    """x + dropout(W2 · dropout(GELU(W1 · LayerNorm(x))))."""

    def __init__(self, dim: int, hidden: int, dropout: float) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.linear1 = nn.Linear(dim, hidden)
        self.linear2 = nn.Linear(hidden, dim)
        self.dropout = nn.Dropout(dropout)
        self.drop_out = nn.Dropout(dropout)

    def forward(self, x: Tensor) -> Tensor:
        h = self.dropout(nn.functional.gelu(self.linear1(self.norm(x))))
        return x + self.drop_out(self.linear2(h))


class EncoderDecoder(nn.Module):
    """Transformer encoder over feature-map tokens and decoder of learned queries (from zero
    targets), each closed by a LayerNorm."""

    def __init__(
        self,
        dim: int,
        heads: int,
        feedforward: int,
        dropout: float,
        encoder_layers: int,
        decoder_layers: int,
    ) -> None:
        super().__init__()
        self.encoder = nn.ModuleList(
            EncoderLayer(dim, heads, feedforward, dropout) for _ in range(encoder_layers)
        )
        self.encoder_norm = nn.LayerNorm(dim)
        self.decoder = nn.ModuleList(
            DecoderLayer(dim, heads, feedforward, dropout) for _ in range(decoder_layers)
        )
        self.decoder_norm = nn.LayerNorm(dim)
        for p in self.parameters():
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)

    def forward(self, tokens: Tensor, pos: Tensor, queries: Tensor) -> Tensor:
        """tokens [B, N, d], pos [N, d], queries [S, d] -> decoded queries [B, S, d]."""
        memory = tokens
        for layer in self.encoder:
            memory = layer(memory, pos)
        memory = self.encoder_norm(memory)
        target = tokens.new_zeros(tokens.shape[0], *queries.shape)
        for layer in self.decoder:
            target = layer(target, memory, pos, queries)
        return self.decoder_norm(target)


def _head(dim: int, out_dim: int, hidden: int) -> nn.Sequential:
    head = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, out_dim))
    for layer in (head[0], head[2]):
        nn.init.xavier_uniform_(layer.weight)
    return head


class MSTransformer(PoseRegressor):
    """image [B, 3, H, W] -> z_x, z_q [B, d] (the selected scene's decoded queries) ->
    x [B, 3] (m), q [B, 4]; `Latents.scene_logits` [B, n_scenes] when n_scenes > 1.

    `encode(images, scene)` selects the given scene's queries (training, as the public code
    does with the true scene) or, with scene=None, the classifier's argmax.
    """

    def __init__(
        self,
        backbone: Backbone,
        n_scenes: int = 1,
        latent_dim: int = 256,
        heads: int = 4,
        feedforward: int = 256,
        dropout: float = 0.1,
        encoder_layers: int = 6,
        decoder_layers: int = 6,
        head_hidden: int = 1024,
    ) -> None:
        super().__init__()
        if backbone.name not in REDUCTION_TAPS:
            raise ValueError(
                f"MSTransformer: no feature taps for backbone {backbone.name!r}; "
                f"choose one of {sorted(REDUCTION_TAPS)}"
            )
        if latent_dim % heads:
            raise ValueError(
                f"MSTransformer: latent_dim={latent_dim} is not divisible by heads={heads}"
            )
        self.latent_dim = latent_dim
        self.n_scenes = n_scenes
        self.backbone = MultiScaleFeatures(backbone)
        self.position = LearnedPositionEncoding(latent_dim)
        self.proj_x = nn.Conv2d(self.backbone.coarse.channels, latent_dim, 1)
        self.proj_q = nn.Conv2d(self.backbone.fine.channels, latent_dim, 1)
        layers = (latent_dim, heads, feedforward, dropout, encoder_layers, decoder_layers)
        self.transformer_x = EncoderDecoder(*layers)
        self.transformer_q = EncoderDecoder(*layers)
        self.queries_x = nn.Embedding(n_scenes, latent_dim)
        self.queries_q = nn.Embedding(n_scenes, latent_dim)
        self.scene_head = nn.Linear(2 * latent_dim, 1) if n_scenes > 1 else None
        self.head_x = _head(latent_dim, 3, head_hidden)
        self.head_q = _head(latent_dim, 4, head_hidden)

    def decode(self, images: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """images -> decoded queries of every scene, x and q [B, S, d], and the scene
        logits [B, S] (zeros for a single scene)."""
        fine, coarse = self.backbone(images)
        decoded = []
        for fmap, proj, transformer, queries in (
            (coarse, self.proj_x, self.transformer_x, self.queries_x),
            (fine, self.proj_q, self.transformer_q, self.queries_q),
        ):
            tokens = proj(fmap).flatten(2).transpose(1, 2)  # [B, h*w, d]
            pos = self.position(*fmap.shape[-2:])
            decoded.append(transformer(tokens, pos, queries.weight))
        dec_x, dec_q = decoded
        if self.scene_head is None:  # one scene: nothing to classify, no unused parameters
            return dec_x, dec_q, dec_x.new_zeros(dec_x.shape[:2])
        logits = self.scene_head(torch.cat([dec_x, dec_q], dim=-1)).squeeze(-1)
        return dec_x, dec_q, logits

    def encode(self, images: Tensor, scene: Tensor | None = None) -> Latents:
        dec_x, dec_q, logits = self.decode(images)
        chosen = (logits.argmax(-1) if scene is None else scene).view(-1, 1, 1)
        index = chosen.expand(-1, 1, self.latent_dim)  # a gather keeps the batch symbolic
        scene_logits = logits if self.n_scenes > 1 else None
        return Latents(
            dec_x.gather(1, index).squeeze(1), dec_q.gather(1, index).squeeze(1), scene_logits
        )

    def regress(self, latents: Latents) -> Tensor:
        return torch.cat([self.head_x(latents.x), self.head_q(latents.q)], dim=-1)

    def scene_poses(self, images: Tensor) -> Tensor | None:
        if self.scene_head is None:
            return None
        dec_x, dec_q, _ = self.decode(images)
        return normalize_pose(torch.cat([self.head_x(dec_x), self.head_q(dec_q)], dim=-1))

    def scene_latents(self, images: Tensor) -> Tensor | None:
        if self.scene_head is None:
            return None
        dec_x, dec_q, _ = self.decode(images)
        return torch.cat([dec_x, dec_q], dim=-1)
