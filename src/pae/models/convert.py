"""Weights released with the public MS-Transformer and PAE code, loaded into pae's modules.

MS-Transformer: the public `EMSTransPoseNet` state dict (shared regression heads, as the PAE
paper's teacher) with its EfficientNet-B0 backbone of the `efficientnet_pytorch` package. Its
backbone keys are renamed to torchvision's `efficientnet_b0().features`; blocks past the
stride-16 map, the last 1x1 convolution and the classifier are not used and dropped. Two
differences remain in the backbone's arithmetic: the public backbone pads its stride-2
convolutions TensorFlow-style ("same": one pixel less at the top/left) and uses BatchNorm
eps 1e-3 (torchvision: symmetric padding, eps 1e-5), so features shift slightly; fine-tune
briefly before comparing figures. Build the model with `heads=8`: the public configs ask
for 4 heads under a key (`nheads`) its transformer does not read, so it runs with its default
of 8; the weights' shapes are the same either way, only the outputs differ.

PAE: the public `PoseEncoder` / `MultiSCenePoseEncoder` state dicts. Their Fourier features
are ordered (input, then per band: sin of every coordinate, cos of every coordinate); pae's
are (input, then per band and coordinate: sin, cos), so the first layer's input columns are
permuted.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import Tensor, nn

from pae.core.checkpoints import read_checkpoint
from pae.core.errors import CheckpointError
from pae.models.ms_transformer import MSTransformer
from pae.models.pae import PoseAutoEncoder

EFFICIENTNET_B0_STAGE_BLOCKS = (1, 2, 2, 3, 3, 4, 1)
"""MBConv blocks per stage; `efficientnet_pytorch` numbers them 0..15 in one list."""

_BLOCK_PARTS = {
    "_expand_conv": ("expand", "0"),
    "_bn0": ("expand", "1"),
    "_depthwise_conv": ("depthwise", "0"),
    "_bn1": ("depthwise", "1"),
    "_se_reduce": ("se", "fc1"),
    "_se_expand": ("se", "fc2"),
    "_project_conv": ("project", "0"),
    "_bn2": ("project", "1"),
}
"""`efficientnet_pytorch` block module -> (torchvision MBConv slot, module within the slot)."""
_OUTER = {"_conv_stem": "0.0", "_bn0": "0.1", "_conv_head": "8.0", "_bn1": "8.1"}
_TRANSFORMER_PARTS = {
    "encoder": {
        "norm1": "norm_attn",
        "norm2": "ff.norm",
        "linear1": "ff.linear1",
        "linear2": "ff.linear2",
        "self_attn": "self_attn",
    },
    "decoder": {
        "norm1": "norm_attn",
        "norm2": "norm_cross",
        "norm3": "ff.norm",
        "linear1": "ff.linear1",
        "linear2": "ff.linear2",
        "self_attn": "self_attn",
        "multihead_attn": "cross_attn",
    },
}
_TOP_LEVEL = {
    "backbone.1.row_embed.weight": "position.row.weight",
    "backbone.1.col_embed.weight": "position.col.weight",
    "query_embed_t.weight": "queries_x.weight",
    "query_embed_rot.weight": "queries_q.weight",
}
_PREFIXES = {
    "input_proj_t.": "proj_x.",
    "input_proj_rot.": "proj_q.",
    "scene_embed.": "scene_head.",
    "regressor_head_t.fc_h.": "head_x.0.",
    "regressor_head_t.fc_o.": "head_x.2.",
    "regressor_head_rot.fc_h.": "head_q.0.",
    "regressor_head_rot.fc_o.": "head_q.2.",
}
_TRANSFORMERS = {"transformer_t": "transformer_x", "transformer_rot": "transformer_q"}


def _efficientnet_key(key: str) -> str | None:
    """An `efficientnet_pytorch` EfficientNet-B0 key -> torchvision `features` key; None for
    keys it does not know. The classifier (`_fc.`) is the caller's to drop."""
    module, _, leaf = key.rpartition(".")
    if module in _OUTER:
        return f"{_OUTER[module]}.{leaf}"
    block = re.fullmatch(r"_blocks\.(\d+)\.(\w+)", module)
    if block is None or block[2] not in _BLOCK_PARTS:
        return None
    index, (slot, inner) = int(block[1]), _BLOCK_PARTS[block[2]]
    stage, first = 0, 0
    while stage < len(EFFICIENTNET_B0_STAGE_BLOCKS) - 1 and (
        index >= first + EFFICIENTNET_B0_STAGE_BLOCKS[stage]
    ):
        first += EFFICIENTNET_B0_STAGE_BLOCKS[stage]
        stage += 1
    # the first block has expansion ratio 1, hence no expand convolution
    slots = ("expand", "depthwise", "se", "project")[0 if index else 1 :]
    if slot not in slots:
        return None
    return f"{stage + 1}.{index - first}.block.{slots.index(slot)}.{inner}.{leaf}"


def _transformer_key(key: str) -> str | None:
    match = re.fullmatch(r"(transformer_t|transformer_rot)\.(encoder|decoder)\.(.+)", key)
    if match is None:
        return None
    model, part, rest = _TRANSFORMERS[match[1]], match[2], match[3]
    if rest.startswith("norm."):
        return f"{model}.{part}_norm.{rest.removeprefix('norm.')}"
    layer = re.fullmatch(r"layers\.(\d+)\.([a-z_0-9]+)\.(.+)", rest)
    if layer is None or layer[2] not in _TRANSFORMER_PARTS[part]:
        return None
    return f"{model}.{part}.{layer[1]}.{_TRANSFORMER_PARTS[part][layer[2]]}.{layer[3]}"


def convert_ms_transformer_state_dict(state: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """Public EMSTransPoseNet state dict -> MSTransformer (backbone=efficientnet_b0) keys.

    Backbone weights come out under `backbone.stages.`, all stages of EfficientNet-B0 (the
    loader keeps those the model has). Raises CheckpointError naming the first key it does
    not know (per-scene heads of the public `MSTransPoseNet` included).
    """
    out: dict[str, Tensor] = {}
    for key, value in state.items():
        key = key.removeprefix("module.")
        if key.startswith("backbone.0.body."):
            new = _efficientnet_key(key.removeprefix("backbone.0.body."))
            if new is None and not key.startswith("backbone.0.body._fc."):
                raise CheckpointError(f"unknown EfficientNet-B0 backbone key {key!r}")
            if new is not None:
                out[f"backbone.stages.{new}"] = value
            continue
        new = _TOP_LEVEL.get(key) or _transformer_key(key)
        if new is None:
            prefix = next((p for p in _PREFIXES if key.startswith(p)), None)
            if prefix is None:
                raise CheckpointError(f"unknown MS-Transformer key {key!r}")
            new = _PREFIXES[prefix] + key.removeprefix(prefix)
        out[new] = value
    return out


def fourier_permutation(dims: int, L: int) -> Tensor:
    """Column order: pae's Fourier feature j is the public code's feature perm[j], for
    `dims` coordinates and L bands (input included). -> long [dims * (2L + 1)]."""
    perm = list(range(dims))
    for band in range(L):
        for coord in range(dims):
            for func in range(2):  # sin, cos
                perm.append(dims + band * 2 * dims + func * dims + coord)
    return torch.tensor(perm)


def convert_pae_state_dict(state: Mapping[str, Tensor], L: int) -> dict[str, Tensor]:
    """Public PoseEncoder / MultiSCenePoseEncoder state dict (L Fourier bands; L=0: raw pose)
    -> PoseAutoEncoder keys, first-layer columns in pae's Fourier order."""
    out: dict[str, Tensor] = {}
    for key, value in state.items():
        match = re.fullmatch(r"(x|q)_encoder\.(\d+)\.(weight|bias)", key.removeprefix("module."))
        if match is None:
            raise CheckpointError(f"unknown PAE key {key!r}")
        branch, layer, leaf = match[1], int(match[2]), match[3]
        if layer == 0 and leaf == "weight":
            dims = 3 if branch == "x" else 4
            pose_dim = dims * (2 * L + 1)
            if value.shape[1] < pose_dim:
                raise CheckpointError(
                    f"PAE key {key!r}: {value.shape[1]} inputs, fewer than the {pose_dim} of "
                    f"{dims} coordinates with L={L} Fourier bands"
                )
            perm = torch.cat([fourier_permutation(dims, L), torch.arange(pose_dim, value.shape[1])])
            value = value[:, perm]
        out[f"branch_{branch}.{layer}.{leaf}"] = value
    return out


def _load_strict(model: nn.Module, state: dict[str, Tensor], source: str) -> None:
    own = model.state_dict()
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    if missing:
        raise CheckpointError(f"{source}: no weights for {missing[0]!r} ({len(missing)} missing)")
    if unexpected:
        raise CheckpointError(f"{source}: unexpected key {unexpected[0]!r}")
    for key, value in state.items():
        if value.shape != own[key].shape:
            raise CheckpointError(
                f"{source}: {key!r} has shape {tuple(value.shape)}, the model expects "
                f"{tuple(own[key].shape)}"
            )
    model.load_state_dict(state)


def load_public_ms_transformer(
    model: MSTransformer, state: Mapping[str, Tensor] | str | Path
) -> MSTransformer:
    """Load a public EMSTransPoseNet state dict (or a file holding one) into `model`; backbone
    stages past the model's stride-16 map, and the scene classifier of a one-scene model,
    are ignored."""
    source = str(state) if isinstance(state, str | Path) else "MS-Transformer state dict"
    raw = read_checkpoint(state) if isinstance(state, str | Path) else state
    own = model.state_dict()
    converted = {
        k: v
        for k, v in convert_ms_transformer_state_dict(raw).items()
        if k in own or not k.startswith(("backbone.stages.", "scene_head."))
    }
    _load_strict(model, converted, source)
    return model


def load_public_pae(
    model: PoseAutoEncoder, state: Mapping[str, Tensor] | str | Path
) -> PoseAutoEncoder:
    """Load a public PoseEncoder / MultiSCenePoseEncoder state dict (or a file holding one)
    into `model` (built with the same L, hidden sizes and n_scenes)."""
    source = str(state) if isinstance(state, str | Path) else "PAE state dict"
    raw = read_checkpoint(state) if isinstance(state, str | Path) else state
    _load_strict(model, convert_pae_state_dict(raw, model.fourier.L), source)
    return model
