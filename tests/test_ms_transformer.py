"""MS-Transformer teacher, multi-scene PAE, refinement within the predicted scene, and the
converters for the public code's state dicts."""

from __future__ import annotations

import itertools
import json
import re
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from pae.core.checkpoints import CheckpointError, load_teacher
from pae.localize import main as localize
from pae.models.backbones import Backbone
from pae.models.base import Latents
from pae.models.convert import (
    fourier_permutation,
    load_public_ms_transformer,
    load_public_pae,
)
from pae.models.ms_transformer import REDUCTION_TAPS, MSTransformer
from pae.models.pae import PoseAutoEncoder
from pae.refine import PoseIndex, PositionRefiner
from pae.train import run
from tests.figures import WORSE_THAN_MEAN_POSE, assert_error_figure, label_reference

SMALL = {
    "latent_dim": 32,
    "heads": 4,
    "feedforward": 64,
    "encoder_layers": 1,
    "decoder_layers": 1,
    "head_hidden": 64,
}


def small_model(backbone: str = "small_cnn", n_scenes: int = 3) -> MSTransformer:
    return MSTransformer(Backbone(backbone), n_scenes=n_scenes, **SMALL)


@pytest.mark.parametrize("name", sorted(REDUCTION_TAPS))
def test_every_backbone_shapes_and_backward(name: str) -> None:
    torch.manual_seed(0)
    model = small_model(name)
    images = torch.randn(2, 3, 64, 64)
    fine, coarse = model.backbone(images)
    assert fine.shape == (2, REDUCTION_TAPS[name][0].channels, 8, 8)
    assert coarse.shape == (2, REDUCTION_TAPS[name][1].channels, 4, 4)
    pose, latents = model(images, torch.tensor([0, 2]))
    assert pose.shape == (2, 7)
    assert latents.x.shape == latents.q.shape == (2, 32)
    assert latents.scene_logits is not None and latents.scene_logits.shape == (2, 3)
    loss = pose.square().sum() + torch.nn.functional.cross_entropy(
        latents.scene_logits, torch.tensor([0, 2])
    )
    loss.backward()
    for part in (
        model.backbone,
        model.proj_x,
        model.proj_q,
        model.transformer_x,
        model.transformer_q,
        model.scene_head,
        model.head_x,
        model.head_q,
    ):
        grads = [p.grad for p in part.parameters()]
        assert any(g is not None and g.abs().sum() > 0 for g in grads), type(part).__name__


def test_given_scene_selects_its_queries_and_none_selects_the_argmax() -> None:
    torch.manual_seed(0)
    model = small_model().eval()
    images = torch.randn(4, 3, 56, 56)
    dec_x, dec_q, logits = model.decode(images)
    scene = torch.tensor([2, 0, 1, 2])
    given = model.encode(images, scene)
    assert torch.allclose(given.x, dec_x[torch.arange(4), scene])
    assert torch.allclose(given.q, dec_q[torch.arange(4), scene])
    predicted = model.encode(images)
    chosen = logits.argmax(-1)
    assert torch.allclose(predicted.x, dec_x[torch.arange(4), chosen])
    assert torch.equal(model.estimate(images, scene).scene, chosen)
    single = small_model(n_scenes=1)
    assert single.scene_head is None and single.encode(images).scene_logits is None


def test_oversized_feature_map_is_a_clear_error() -> None:
    model = small_model()
    with pytest.raises(ValueError, match="exceeds the positional encoding"):
        model(torch.randn(1, 3, 1024, 64))


def test_multi_scene_pae_fourier_encodes_the_scene_even_without_pose_bands() -> None:
    pae = PoseAutoEncoder(latent_dim=8, hidden=(16,), L=0, n_scenes=3)
    assert pae.branch_x[0].in_features == 3 + 13 and pae.branch_q[0].in_features == 4 + 13
    assert PoseAutoEncoder(latent_dim=8, hidden=(16,), L=0).branch_x[0].in_features == 3


def _force_scene(model: MSTransformer, scene: int) -> None:
    """Make the scene classifier prefer `scene` for every image."""
    offset = torch.zeros(model.n_scenes, 1)
    offset[scene] = 100.0
    model.scene_head.register_forward_hook(lambda module, args, out: out + offset)


def test_multi_scene_refinement_retrieves_only_within_the_predicted_scene() -> None:
    torch.manual_seed(0)
    model = small_model().eval()
    _force_scene(model, 2)
    true_scene = torch.tensor([0, 1, 0, 1])
    answer = model.estimate(torch.randn(4, 3, 56, 56), true_scene)
    assert torch.equal(answer.scene, torch.full((4,), 2))
    # the same train poses in every scene: only the scene id tells the neighbours apart
    poses = torch.cat([torch.randn(20, 3), torch.nn.functional.normalize(torch.randn(20, 4))], 1)
    store_poses, store_scenes = poses.repeat(3, 1), torch.arange(3).repeat_interleave(20)
    pae = PoseAutoEncoder(latent_dim=32, hidden=(16,), L=2, n_scenes=3)
    seen: list[Tensor] = []

    def encoder(p: Tensor, s: Tensor | None) -> Latents:
        assert s is not None
        seen.append(s)
        return pae(p, s)

    refiner = PositionRefiner(PoseIndex(store_poses, store_scenes), encoder, k=3)
    result = refiner(answer.latents, answer.pose, answer.scene)
    assert (store_scenes[result.neighbour_indices] == 2).all()
    assert torch.equal(torch.cat(seen), torch.full((12,), 2))


# The public code's parameter names and shapes, written out from its architecture.
B0_STAGES = [  # expand ratio, kernel, input channels, output channels, repeats
    (1, 3, 32, 16, 1),
    (6, 3, 16, 24, 2),
    (6, 5, 24, 40, 2),
    (6, 3, 40, 80, 3),
    (6, 5, 80, 112, 3),
    (6, 5, 112, 192, 4),
    (6, 3, 192, 320, 1),
]


def _bn(prefix: str, channels: int) -> dict[str, tuple[int, ...]]:
    shapes = {
        f"{prefix}.{leaf}": (channels,)
        for leaf in ("weight", "bias", "running_mean", "running_var")
    }
    return shapes | {f"{prefix}.num_batches_tracked": ()}


def public_efficientnet_shapes() -> dict[str, tuple[int, ...]]:
    shapes = {"_conv_stem.weight": (32, 3, 3, 3), **_bn("_bn0", 32)}
    index = 0
    for expand, kernel, cin, cout, repeats in B0_STAGES:
        for r in range(repeats):
            inp = cin if r == 0 else cout
            mid, squeeze, p = inp * expand, max(1, int(inp * 0.25)), f"_blocks.{index}"
            if expand != 1:
                shapes |= {f"{p}._expand_conv.weight": (mid, inp, 1, 1), **_bn(f"{p}._bn0", mid)}
            shapes |= {f"{p}._depthwise_conv.weight": (mid, 1, kernel, kernel)}
            shapes |= _bn(f"{p}._bn1", mid)
            shapes |= {
                f"{p}._se_reduce.weight": (squeeze, mid, 1, 1),
                f"{p}._se_reduce.bias": (squeeze,),
                f"{p}._se_expand.weight": (mid, squeeze, 1, 1),
                f"{p}._se_expand.bias": (mid,),
                f"{p}._project_conv.weight": (cout, mid, 1, 1),
            }
            shapes |= _bn(f"{p}._bn2", cout)
            index += 1
    shapes |= {"_conv_head.weight": (1280, 320, 1, 1), **_bn("_bn1", 1280)}
    return shapes | {"_fc.weight": (1000, 1280), "_fc.bias": (1000,)}


def _attention(prefix: str, d: int) -> dict[str, tuple[int, ...]]:
    return {
        f"{prefix}.in_proj_weight": (3 * d, d),
        f"{prefix}.in_proj_bias": (3 * d,),
        f"{prefix}.out_proj.weight": (d, d),
        f"{prefix}.out_proj.bias": (d,),
    }


def _linear(prefix: str, out_dim: int, in_dim: int) -> dict[str, tuple[int, ...]]:
    return {f"{prefix}.weight": (out_dim, in_dim), f"{prefix}.bias": (out_dim,)}


def public_ms_transformer_shapes(
    d: int, ff: int, layers: int, scenes: int, hidden: int
) -> dict[str, tuple[int, ...]]:
    shapes = {f"backbone.0.body.{k}": v for k, v in public_efficientnet_shapes().items()}
    shapes |= {
        "backbone.1.row_embed.weight": (50, d // 2),
        "backbone.1.col_embed.weight": (50, d // 2),
    }
    for name in ("transformer_t", "transformer_rot"):
        for i in range(layers):
            enc, dec = f"{name}.encoder.layers.{i}", f"{name}.decoder.layers.{i}"
            shapes |= _attention(f"{enc}.self_attn", d)
            shapes |= _attention(f"{dec}.self_attn", d) | _attention(f"{dec}.multihead_attn", d)
            for layer in (enc, dec):
                shapes |= _linear(f"{layer}.linear1", ff, d) | _linear(f"{layer}.linear2", d, ff)
            for norm in (
                f"{enc}.norm1",
                f"{enc}.norm2",
                f"{dec}.norm1",
                f"{dec}.norm2",
                f"{dec}.norm3",
                f"{name}.encoder.norm",
                f"{name}.decoder.norm",
            ):
                shapes |= {f"{norm}.weight": (d,), f"{norm}.bias": (d,)}
    shapes |= {
        "input_proj_t.weight": (d, 112, 1, 1),
        "input_proj_t.bias": (d,),
        "input_proj_rot.weight": (d, 40, 1, 1),
        "input_proj_rot.bias": (d,),
        "query_embed_t.weight": (scenes, d),
        "query_embed_rot.weight": (scenes, d),
    }
    shapes |= _linear("scene_embed", 1, 2 * d)
    for name, out_dim in (("regressor_head_t", 3), ("regressor_head_rot", 4)):
        shapes |= _linear(f"{name}.fc_h", hidden, d) | _linear(f"{name}.fc_o", out_dim, hidden)
    return shapes


def random_state(shapes: dict[str, tuple[int, ...]]) -> dict[str, Tensor]:
    """Small random values (positive running variances, a batch count) of the given shapes."""
    generator = torch.Generator().manual_seed(0)
    state = {}
    for key, shape in shapes.items():
        if key.endswith("num_batches_tracked"):
            state[key] = torch.tensor(7)
        else:
            state[key] = 0.05 * torch.randn(shape, generator=generator)
        if key.endswith("running_var"):
            state[key] = state[key].abs() + 1.0
    return state


@pytest.fixture(scope="module")
def public_state() -> dict[str, Tensor]:
    return random_state(public_ms_transformer_shapes(d=32, ff=64, layers=1, scenes=3, hidden=64))


def test_public_ms_transformer_state_dict_loads(public_state: dict[str, Tensor]) -> None:
    model = load_public_ms_transformer(small_model("efficientnet_b0"), public_state)
    pairs = {
        "query_embed_t.weight": model.queries_x.weight,
        "query_embed_rot.weight": model.queries_q.weight,
        "backbone.1.row_embed.weight": model.position.row.weight,
        "scene_embed.weight": model.scene_head.weight,
        "regressor_head_rot.fc_o.bias": model.head_q[2].bias,
        "input_proj_t.weight": model.proj_x.weight,
        "transformer_t.decoder.layers.0.multihead_attn.in_proj_weight": model.transformer_x.decoder[
            0
        ].cross_attn.in_proj_weight,
        "transformer_rot.encoder.layers.0.norm2.weight": model.transformer_q.encoder[
            0
        ].ff.norm.weight,
        "transformer_rot.decoder.norm.bias": model.transformer_q.decoder_norm.bias,
        "backbone.0.body._conv_stem.weight": model.backbone.stages[0][0].weight,
        "backbone.0.body._blocks.0._depthwise_conv.weight": model.backbone.stages[1][0]
        .block[0][0]
        .weight,
        "backbone.0.body._blocks.4._project_conv.weight": model.backbone.stages[3][1]
        .block[3][0]
        .weight,
        "backbone.0.body._blocks.10._se_expand.bias": model.backbone.stages[5][2].block[2].fc2.bias,
    }
    for key, param in pairs.items():
        assert torch.equal(public_state[key], param), key
    pose, latents = model.eval()(torch.randn(1, 3, 64, 64))
    assert torch.isfinite(pose).all() and latents.scene_logits is not None
    one_scene = public_ms_transformer_shapes(d=32, ff=64, layers=1, scenes=1, hidden=64)
    single = load_public_ms_transformer(small_model("efficientnet_b0", 1), random_state(one_scene))
    assert single.scene_head is None


def test_public_ms_transformer_mismatches_name_the_key(
    public_state: dict[str, Tensor], tmp_path: Path
) -> None:
    missing = {k: v for k, v in public_state.items() if k != "scene_embed.bias"}
    with pytest.raises(CheckpointError, match=re.escape("no weights for 'scene_head.bias'")):
        load_public_ms_transformer(small_model("efficientnet_b0"), missing)
    per_scene = public_state | {"regressor_head_t.0.fc_h.weight": torch.zeros(64, 32)}
    with pytest.raises(
        CheckpointError, match=re.escape("unknown MS-Transformer key 'regressor_head_t.0")
    ):
        load_public_ms_transformer(small_model("efficientnet_b0"), per_scene)
    path = tmp_path / "ems.pth"
    torch.save(public_state, path)
    with pytest.raises(CheckpointError, match=re.escape(f"{path}: 'queries_x.weight' has shape")):
        load_public_ms_transformer(small_model("efficientnet_b0", n_scenes=4), path)


def public_fourier(p: Tensor, bands: int) -> Tensor:
    """The public code's order: input, then per band sin of all coordinates, cos of all."""
    parts = [p]
    for band in range(bands):
        parts += [torch.sin(p * 2.0**band), torch.cos(p * 2.0**band)]
    return torch.cat(parts, dim=-1)


def test_fourier_permutation_maps_public_order_to_ours() -> None:
    from pae.models.pae import FourierFeatures

    p = torch.randn(5, 3)
    ours, public = FourierFeatures(4)(p), public_fourier(p, 4)
    assert torch.equal(ours, public[:, fourier_permutation(3, 4)])


@pytest.mark.parametrize(("L", "n_scenes"), [(6, 1), (6, 3), (0, 1)])
def test_public_pae_state_dict_gives_the_same_latents(L: int, n_scenes: int) -> None:
    generator = torch.Generator().manual_seed(0)
    hidden, d = (64, 128, 256), 16
    scene_dim = 13 if n_scenes > 1 else 0
    public: dict[str, Tensor] = {}
    for branch, dims in (("x", 3), ("q", 4)):
        sizes = [dims * (2 * L + 1) + scene_dim, *hidden, d]
        for i, (a, b) in enumerate(itertools.pairwise(sizes)):
            public[f"{branch}_encoder.{2 * i}.weight"] = (
                torch.randn(b, a, generator=generator) / a**0.5
            )
            public[f"{branch}_encoder.{2 * i}.bias"] = torch.randn(b, generator=generator)
    pae = load_public_pae(PoseAutoEncoder(d, hidden, L=L, n_scenes=n_scenes), public)
    poses = torch.cat([torch.randn(6, 3), torch.nn.functional.normalize(torch.randn(6, 4))], 1)
    scene = torch.tensor([0, 1, 2, 0, 1, 2]) if n_scenes > 1 else None
    ours = pae(poses, scene)

    def reference(branch: str, coords: Tensor) -> Tensor:
        h = public_fourier(coords, L)
        if scene is not None:
            h = torch.cat([h, public_fourier(scene.float().unsqueeze(1), 6)], 1)
        for i in range(len(hidden) + 1):
            h = h @ public[f"{branch}_encoder.{2 * i}.weight"].T
            h = h + public[f"{branch}_encoder.{2 * i}.bias"]
            h = torch.relu(h) if i < len(hidden) else h
        return h

    assert torch.allclose(ours.x, reference("x", poses[:, :3]), atol=1e-4)
    assert torch.allclose(ours.q, reference("q", poses[:, 3:]), atol=1e-4)
    with pytest.raises(CheckpointError, match=re.escape("unknown PAE key 'x_head.0.weight'")):
        load_public_pae(pae, public | {"x_head.0.weight": torch.zeros(1)})


def test_ms_transformer_pipeline_reports_scene_accuracy(
    compose_train: Callable[..., DictConfig], tiny_root: Path, tmp_path: Path, capsys
) -> None:
    cfg = compose_train(
        "stage=pipeline",
        "teacher=ms_transformer",
        "teacher.model.latent_dim=16",
        "teacher.model.feedforward=32",
        "teacher.model.encoder_layers=1",
        "teacher.model.decoder_layers=1",
        "teacher.model.head_hidden=32",
        "teacher.max_epochs=1",
        "student.max_epochs=1",
        "stage.steps=[teacher,student,scene_model]",
        "scene_model.max_epochs=1",
        "scene_model.batches_per_epoch=3",
        "render_compare.refiner.rounds=1",
        run_dir=tmp_path,
    )
    (tmp_path / ".hydra").mkdir(parents=True, exist_ok=True)
    saved = {key: value for key, value in cfg.items() if key != "hydra"}  # what Hydra saves
    OmegaConf.save(OmegaConf.create(saved), tmp_path / ".hydra" / "config.yaml")
    run(cfg, tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert 0.0 <= metrics["test/teacher/scene_accuracy"] <= 1.0
    # render-and-compare decides the scene of a multi-scene teacher's queries
    for split in ("val", "test"):
        assert 0.0 <= metrics[f"{split}/render_compare/scene_accuracy"] <= 1.0
        assert 0.0 <= metrics[f"{split}/render_compare/scene_checked_share"] <= 1.0
        for method in ("teacher", "render_compare"):  # the confusion tables count every query
            counts = [
                metrics[f"{split}/{method}/scene_confusion/{true}/{assigned}"]
                for true in ("scene00", "scene01")
                for assigned in ("scene00", "scene01")
            ]
            accuracy = (counts[0] + counts[3]) / sum(counts)
            assert accuracy == pytest.approx(metrics[f"{split}/{method}/scene_accuracy"])
    for key in ("check_below", "probe_scale", "prior_weight", "move_margin"):
        chosen = metrics[f"val/render_compare/scene_{key}"]
        assert metrics[f"test/render_compare/scene_{key}"] == chosen, "chosen on val"
    # the tables in TensorBoard, beside the gallery of poses in the decided scenes
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(tmp_path / "scene_model"), size_guidance={"tensors": 0})
    events.Reload()
    assert "test/scene_confusion/text_summary" in events.Tags()["tensors"]
    assert "test/render_compare/gallery/scene01" in events.Tags()["images"]
    # pae-localize runs the same scene decision: the run's test figures
    out = tmp_path / "localized.csv"
    labels = tiny_root / "labels" / "all_test.csv"
    argv = [str(tmp_path), str(labels), "--out", str(out), "--refine", "render_compare"]
    assert localize(argv) == 0
    printed = capsys.readouterr().out
    accuracy = 100 * metrics["test/render_compare/scene_accuracy"]
    assert f"scene accuracy {accuracy:.1f} %" in printed
    assert f"median {metrics['test/render_compare/pos_median_m']:.3f} m" in printed
    upper = WORSE_THAN_MEAN_POSE * label_reference(tiny_root, "test")["scene00/pos_median_m"]
    for method in ("teacher", "student", "refined", "render_compare"):
        assert_error_figure(metrics, f"test/{method}/scene00/pos_median_m", upper)
    teacher = load_teacher(tmp_path / "student" / "checkpoints" / "last.ckpt")
    assert isinstance(teacher.model, MSTransformer) and teacher.model.latent_dim == 16
