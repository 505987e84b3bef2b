"""The interface of scene models: what render-and-compare refinement renders at a pose, and
what the scene_model step reads from a model's class to build and train it."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import torch
from omegaconf import DictConfig
from torch import Tensor, nn


class SceneRendering(NamedTuple):
    """Images rendered at ``B`` poses.

    rgb: [B, 3, H, W] in [0, 1]; depth: [B, H, W] metres along the optical axis, or None for
    models that know no geometry; opacity: [B, H, W] in [0, 1] (how much of each pixel the
    model explains), or None.
    """

    rgb: Tensor
    depth: Tensor | None = None
    opacity: Tensor | None = None


@dataclass(frozen=True)
class SceneModelInputs:
    """What the scene_model step gives a scene model's ``build``.

    data: the run's data module, set up (read its train split only: ``train_poses()``,
    ``appearance_ids("train", ...)``, ``n_scenes``, ``scene_names``); appearance: the
    ``scene_model.appearance`` setting (``sequence`` or ``image``); load: a checkpoint key of
    the class's ``needs`` -> its loaded model (``pae.core.checkpoints.LoadedModel``), checked to
    have been trained on ``data``.
    """

    data: Any
    appearance: str
    load: Callable[[str], Any]


class SceneModel(nn.Module):
    """A model of the scenes a dataset shows, rendered at camera poses.

    A subclass is a plugin: ``conf/scene_model/<name>.yaml`` names it as ``model._target_``
    and the scene_model step reads the rest from the class:

    - ``has_depth``: whether renderings carry depth (render-and-compare then projects the
      rendered surface into candidate cameras instead of rendering every candidate);
    - ``trains``: whether the step fits it to the train images' rays (``render_rays``,
      ``with_appearance``, ``total_variation``) and writes its checkpoint; otherwise it is
      built and evaluated as it is;
    - ``needs``: the checkpoint keys its ``build`` loads (given on the command line or made by
      an earlier step; checked before anything trains);
    - ``fits_depth``: whether the fit can ask its rays' light to end at a depth
      (``depth_error``: ``scene_model.depth_rays``);
    - ``from_run`` and ``build_keys``: the constructor arguments ``build`` fills in and the
      config keys it reads itself; ``check_config``: the ranges its signature cannot state
      (``pae.core.checks.check_constructor`` reads all three before any work).
    """

    has_depth: ClassVar[bool] = True
    trains: ClassVar[bool] = False
    fits_depth: ClassVar[bool] = False
    needs: ClassVar[tuple[str, ...]] = ()
    from_run: ClassVar[tuple[str, ...]] = ()
    build_keys: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def check_config(cls, cfg: DictConfig, key: str) -> None:
        """Check the model config at ``key`` of ``cfg`` (ConfigError naming the key)."""

    @classmethod
    def build(
        cls, config: dict[str, Any], inputs: SceneModelInputs
    ) -> tuple[SceneModel, dict[str, Any] | None]:
        """The model from its config (``_target_`` removed) and the run -> (the model, the
        constructor arguments a checkpoint stores to rebuild it; None: nothing to store)."""
        return cls(**config), config

    def render(
        self,
        poses: Tensor,
        scenes: Tensor,
        intrinsics: Tensor,
        width: int,
        height: int,
        surface_share: float = 0.0,
    ) -> SceneRendering:
        """Render ``B`` cameras: poses [B, 7] (camera-to-world), scene ids [B], intrinsics
        [B, 4] (fx, fy, cx, cy in px of ``width × height`` images). ``surface_share``: a model
        whose depth is a volume's light (the voxel grid) returns, for a share in (0, 1), the
        depth by which each ray has gathered that share of its opacity instead of the light's
        mean depth; others ignore it."""
        raise NotImplementedError

    def render_rays(
        self, origins: Tensor, directions: Tensor, scenes: Tensor, jitter: bool = False
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Models that train: rays [R, 3] (world frame) of scenes [R] -> rgb [R, 3], depth [R],
        opacity [R]; ``jitter``: random sample offsets (training)."""
        raise NotImplementedError

    def with_appearance(
        self, rgb: Tensor, appearance: Tensor, pixels: Tensor | None = None
    ) -> Tensor:
        """Renderings [R, 3] as the train image (or sequence) ``appearance`` [R] saw them;
        ``pixels`` [R, 2]: where each ray meets its image, (column, row) scaled to [0, 1]
        (None: unknown)."""
        return rgb

    def depth_error(
        self, origins: Tensor, directions: Tensor, scenes: Tensor, target: Tensor
    ) -> Tensor:
        """Models that fit depth: how far from ``target`` [R] (depth along the directions)
        the light of rays [R, 3] of scenes [R] ends [R], differentiable."""
        raise NotImplementedError

    def total_variation(self) -> Tensor:
        """The smoothness penalty the step adds to the fit (``scene_model.tv_weight``)."""
        return torch.zeros(())

    def fit_stage(self, epoch: int, fresh: bool) -> bool:
        """Models that train, at the start of fit epoch ``epoch`` (``fresh``: no step taken
        yet): change what the fit optimises (the voxel grid grows); whether its parameters
        changed, so that the optimiser is built again."""
        return False


class PaeDecoderSceneModel(SceneModel):
    """The paper's image decoder over PAE encodings as a scene model: a 2-D model that
    knows no geometry and no camera. It renders the view its decoder was trained on (the
    evaluation crop), resized to the requested size; ``intrinsics`` are not read. Built from
    the student's PAE and the decoder checkpoint; nothing to train."""

    has_depth = False
    needs = ("student_ckpt", "decoder_ckpt")
    from_run = ("pae", "decoder")

    def __init__(self, pae: nn.Module, decoder: nn.Module) -> None:
        super().__init__()
        self.pae = pae
        self.decoder = decoder

    @classmethod
    def build(
        cls, config: dict[str, Any], inputs: SceneModelInputs
    ) -> tuple[SceneModel, dict[str, Any] | None]:
        pae, decoder = inputs.load("student_ckpt"), inputs.load("decoder_ckpt")
        return cls(pae.model, decoder.model), None

    def render(
        self,
        poses: Tensor,
        scenes: Tensor,
        intrinsics: Tensor,
        width: int,
        height: int,
        surface_share: float = 0.0,
    ) -> SceneRendering:
        images = self.decoder(self.pae(poses, scenes).joint())
        if images.shape[-2:] != (height, width):
            images = nn.functional.interpolate(images, size=(height, width), mode="area")
        return SceneRendering(images)
