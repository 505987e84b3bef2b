"""Render-and-compare pose refinement against a scene model learned from the train images.

Starting from the teacher's estimate, each query's pose (position and orientation) is aligned
to the query image coarse to fine over an image pyramid (``levels`` compare widths, each half
the next, the finest ``resolution`` px or the query's own width):

1. **Search** at the coarsest level: a first round of ``hypotheses × candidates`` 6-DoF
   perturbations around the start seeds ``hypotheses`` chains (the best-scoring ones, the
   start included); each chain then draws ``candidates`` perturbations around itself per
   round, keeps the best and shrinks its steps after a round without improvement.
2. **Polish** at every level, coarse to fine: ``polish_steps`` Levenberg–Marquardt steps on
   each hypothesis's image residual (:mod:`pae.render_compare.kernels`); after each level but the
   last, the better half of the hypotheses goes on. Before the finest level the scene model is
   rendered again at the best hypothesis (``final_reference_size``) so that the final alignment
   sees the surface densely, from where the camera now is.

Scores are appearance-invariant: the zero-mean normalised cross-correlation (ZNCC) of
band-passed grey images, or (``score="features"``, search only) the mean cosine similarity of
feature maps of a given extractor (the teacher's backbone). A model with depth is rendered
once per query (a wider field of view) and its surface points are projected into each
candidate camera; a model without depth renders every candidate's image (search only).

Every query of a call is refined at once, in chunks of ``chunk`` queries: no Python loop runs
per query. The random draws come from one generator in query order (the chunking changes no
result) or, given ``keys``, from each query's key (the batch changes no result). ``engine``:
compiled loops (numba, CPU) or tensor operations (any device), the same steps (tested equal).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor

from pae.core.camera import camera_rays, project, scale_intrinsics
from pae.core.geometry import matrix_to_quaternion, normalize_quaternion, quaternion_to_matrix
from pae.core.keyed_random import keyed_normals
from pae.core.pose_sampling import perturb
from pae.render_compare.gate import ACCEPT_ALL, GatedPoses, RenderCompareResult, gate
from pae.render_compare.images import (
    band_pass,
    clip_bright,
    float32_arithmetic,
    grey,
    pyramid_widths,
    trimmed_zncc,
)
from pae.render_compare.kernels.numba_polish import polish_compiled
from pae.render_compare.kernels.numba_score import compiled_zncc_scores
from pae.render_compare.kernels.reference import (
    MIN_DEPTH_M,
    NOT_SEEN_SCORE,
    PolishProblem,
    PolishSettings,
    polish_tensor,
)
from pae.render_compare.records import Hypotheses, Level, Reference, Surface
from pae.render_compare.settings import (
    BUILD_KEYS,
    ENGINES,
    SCORES,
    check_settings,
    refiner_defaults,
)
from pae.render_compare.work import RenderCompareWork
from pae.scene_model.base import SceneModel

__all__ = [
    "ACCEPT_ALL",
    "BUILD_KEYS",
    "ENGINES",
    "SCORES",
    "GatedPoses",
    "RenderCompareRefiner",
    "RenderCompareResult",
    "gate",
    "refiner_defaults",
]
"""The refiner's public names (the gate and the result live in ``pae.render_compare.gate``,
the settings' defaults and ranges in ``pae.render_compare.settings``)."""

FeatureExtractor = Callable[[Tensor], Tensor]
"""RGB images [B, 3, H, W] in [0, 1] -> feature maps [B, C, h, w]."""


class RenderCompareRefiner:
    """Render-and-compare refinement of APR estimates against ``scene_model``.

    Search: rounds (at the coarsest level; 0: none), candidates (per hypothesis and round),
    hypotheses (chains kept until the finer levels decide), position_sigma_m,
    orientation_sigma_deg (the first round's steps per axis), shrink (a chain's step factor
    after a round without improvement). Pyramid: resolution, levels, and the compared images'
    filter (highlight_quantile: :func:`clip_bright`; blur_sigma_px, highpass_sigma_px,
    contrast_sigma_px, highpass_levels: :func:`band_pass`). References: reference_size,
    reference_fov_scale (the start's rendering), final_reference_size, final_fov_scale (at the
    best hypothesis before the finest level; 0: none), surface_share (their surface points).
    Polish: polish_steps, polish_damping. Score: min_overlap (else ``NOT_SEEN_SCORE``),
    trim_sigma, trim_passes (:func:`trimmed_zncc`), score (``zncc``, or ``features`` with
    ``features``). seed: of the draws; chunk, gpu_chunk: queries refined at once
    (:meth:`chunk_for`); engine: ``ENGINES``. Each setting's meaning and default:
    ``RenderCompareSettings`` (:meth:`configured`).
    """

    from_run: ClassVar[tuple[str, ...]] = ("scene_model", "features")
    """Arguments its caller supplies (the run's scene model, the teacher's features), never
    configured (``pae.core.checks.check_constructor``)."""

    def __init__(
        self,
        scene_model: SceneModel,
        *,
        rounds: int,
        candidates: int,
        hypotheses: int,
        position_sigma_m: float,
        orientation_sigma_deg: float,
        shrink: float,
        resolution: int,
        levels: int,
        blur_sigma_px: float,
        highpass_sigma_px: float,
        contrast_sigma_px: float,
        highlight_quantile: float,
        highpass_levels: int,
        reference_size: int,
        reference_fov_scale: float,
        final_reference_size: int,
        final_fov_scale: float,
        surface_share: float,
        polish_steps: int,
        polish_damping: float,
        min_overlap: float,
        trim_sigma: float,
        trim_passes: int,
        score: str,
        seed: int,
        chunk: int,
        gpu_chunk: int,
        engine: str,
        features: FeatureExtractor | None = None,
    ) -> None:
        check_settings(**{name: value for name, value in locals().items() if name != "self"})
        self.scene_model = scene_model
        self.rounds, self.candidates, self.hypotheses = rounds, candidates, hypotheses
        self.sigma = (position_sigma_m, math.radians(orientation_sigma_deg))
        self.shrink, self.resolution, self.levels = shrink, resolution, levels
        self.blur_sigma_px, self.highpass_sigma_px = blur_sigma_px, highpass_sigma_px
        self.contrast_sigma_px, self.highpass_levels = contrast_sigma_px, highpass_levels
        self.reference_size, self.reference_fov_scale = reference_size, reference_fov_scale
        self.final_reference_size, self.final_fov_scale = final_reference_size, final_fov_scale
        self.surface_share, self.highlight_quantile = surface_share, highlight_quantile
        self.polish_steps, self.polish_damping = polish_steps, polish_damping
        self.min_overlap, self.trim_sigma, self.trim_passes = min_overlap, trim_sigma, trim_passes
        self.score, self.features, self.seed = score, features, seed
        self.chunk, self.gpu_chunk, self.engine = chunk, gpu_chunk, engine
        self.work = RenderCompareWork()

    @classmethod
    def configured(cls, scene_model: SceneModel, **settings: Any) -> RenderCompareRefiner:
        """The refiner with the default settings (``RenderCompareSettings``,
        :func:`refiner_defaults`), ``settings`` replacing any of them."""
        return cls(scene_model, **(refiner_defaults() | settings))

    def chunk_for(self, device: torch.device) -> int:
        """How many queries are refined at once on ``device``: ``chunk`` on the CPU (what
        stays in its caches), ``gpu_chunk`` elsewhere (few, large kernel launches). The
        draws do not depend on it."""
        return self.chunk if device.type == "cpu" else self.gpu_chunk

    def draw_stream(self) -> Callable[[int], Tensor]:
        """The search's standard-normal draws, made as they are needed: each call ``(n)``
        returns the next ``n`` queries' draws [n, rounds, hypotheses × candidates, 6] from
        the refiner's seed. Each query's share of the stream is padded to whole blocks of 16
        numbers, the unit of torch's CPU normal sampler, so a sequence of calls yields exactly
        the draws of one call for all queries (tested): results never depend on the
        chunking."""
        generator = torch.Generator().manual_seed(self.seed)
        shape = (self.rounds, self.hypotheses * self.candidates, 6)
        count = math.prod(shape)
        padded = -(-count // 16) * 16

        def next_draws(n_queries: int) -> Tensor:
            numbers = torch.randn((n_queries, padded), generator=generator)
            return numbers[:, :count].reshape(n_queries, *shape)

        return next_draws

    def draws(self, n_queries: int, device: torch.device | str = "cpu") -> Tensor:
        """The first ``n_queries`` queries' draws of :meth:`draw_stream`, in query order."""
        return self.draw_stream()(n_queries).to(device)

    def keyed_draws(self, keys: Tensor) -> Tensor:
        """Draws shaped as :meth:`draws` gives them, each from the seed and its key [n]."""
        shape = (self.rounds, self.hypotheses * self.candidates, 6)
        return keyed_normals(self.seed, keys, math.prod(shape)).reshape(len(keys), *shape)

    def _grey(self, rgb: Tensor) -> Tensor:  # the grey images the score compares
        return clip_bright(grey(rgb), self.highlight_quantile)

    def _compiled(self, device: torch.device) -> bool:
        return self.engine == "numba" or (
            self.engine == "auto" and self.score == "zncc" and device.type == "cpu"
        )

    @torch.no_grad()
    def pyramid(self, images: Tensor, intrinsics: Tensor, scenes: Tensor) -> list[Level]:
        """Query images [B, 3, H, W] (RGB in [0, 1]) with intrinsics [B, 4] -> what the
        score compares against at each level, coarse to fine."""
        h, w = images.shape[-2:]
        finest = min(self.resolution, w)
        levels = []
        widths = pyramid_widths(self.resolution, self.levels, w)
        whole = len(widths) - self.highpass_levels if self.highpass_levels else 0
        for index, width in enumerate(widths):
            height = max(4, round(h * width / w))
            small = F.interpolate(images, size=(height, width), mode="area")
            scaled = scale_intrinsics(intrinsics, width / w, height / h)
            if self.score == "features":
                assert self.features is not None
                maps = self.features(small)
                fh, fw = maps.shape[-2:]
                levels.append(
                    Level(maps, scale_intrinsics(scaled, fw / width, fh / height), scenes, (0, 0))
                )
                continue
            scale = 0.0 if index < whole else width / finest
            sigmas = (
                self.blur_sigma_px,
                self.highpass_sigma_px * scale,
                self.contrast_sigma_px * scale,
            )
            target = band_pass(self._grey(small), *sigmas)
            levels.append(Level(target, scaled, scenes, sigmas))
        return levels

    def _reference_intrinsics(
        self, level: Level, width: int, fov_scale: float
    ) -> tuple[Tensor, int, int]:
        """Intrinsics [B, 4] of ``width``-px reference renderings (a wider view centred like
        the query's), their width and height in px."""
        _, _, h, w = level.target.shape
        height = max(4, round(h * width / w))
        scale = width / w / fov_scale
        fx, fy, _, _ = level.intrinsics.unbind(-1)
        centre_x = torch.full_like(fx, (width - 1) / 2)
        centre_y = torch.full_like(fy, (height - 1) / 2)
        return torch.stack([fx * scale, fy * scale, centre_x, centre_y], -1), width, height

    @torch.no_grad()
    def reference(self, poses: Tensor, level: Level, width: int, fov_scale: float) -> Reference:
        """Render the scene model at poses [B, 7] with a ``width``-px reference camera: its
        surface points, its grey image (RGB for the features score) and where the model
        explains the image."""
        intrinsics, width, height = self._reference_intrinsics(level, width, fov_scale)
        with self.work.timed("render"):
            rendering = self.scene_model.render(
                poses, level.scenes, intrinsics, width, height, self.surface_share
            )
        self.work.rendered_rays += len(poses) * width * height
        assert rendering.depth is not None and rendering.opacity is not None
        origins, directions = camera_rays(poses, intrinsics, width, height)
        points = origins + rendering.depth.flatten(1)[..., None] * directions
        image = rendering.rgb if self.score == "features" else self._grey(rendering.rgb)
        valid = (rendering.opacity.flatten(1) > 0.5).to(points.dtype)
        return Reference(points, image, valid, intrinsics[:, 0])

    @torch.no_grad()
    def surface(self, reference: Reference, level: Level) -> Surface:
        """The reference's values as ``level`` compares them: filtered as the level's images
        (its sigmas scaled to the rendering's focal length), or the features' maps."""
        height, width = reference.image.shape[-2:]
        if self.score == "features":
            assert self.features is not None
            maps = self.features(reference.image)
            values = F.interpolate(maps, size=(height, width), mode="bilinear").flatten(2)
        else:
            scale = float((reference.focal / level.intrinsics[:, 0]).mean())
            values = band_pass(reference.image, *(s * scale for s in level.sigmas)).flatten(2)
        return Surface(reference.points, values, reference.valid)

    def _score_projected(self, poses: Tensor, level: Level, surface: Surface) -> Tensor:
        """Scores [B, M] of candidate poses [B, M, 7] with tensor operations: the surface
        projected into each candidate camera, compared with the query where it lands inside
        the image."""
        b, m = poses.shape[:2]
        rotation = quaternion_to_matrix(poses[..., 3:])  # [B, M, 3, 3]
        relative = surface.points[:, None] - poses[..., None, :3]  # [B, M, P, 3]
        local = torch.einsum("bmji,bmpj->bmpi", rotation, relative)
        h, w = level.target.shape[-2:]
        uv = project(local, level.intrinsics[:, None, None])
        inside = (
            (local[..., 2] > MIN_DEPTH_M)
            & (uv[..., 0] >= 0)
            & (uv[..., 0] <= w - 1)
            & (uv[..., 1] >= 0)
            & (uv[..., 1] <= h - 1)
        )
        weights = inside.to(uv.dtype) * surface.valid[:, None]
        grid = torch.stack([uv[..., 0] / (w - 1) * 2 - 1, uv[..., 1] / (h - 1) * 2 - 1], -1)
        sampled = F.grid_sample(
            level.target, grid.view(b, m, -1, 2), align_corners=True, padding_mode="border"
        )  # [B, C, M, P]
        values = surface.values[:, :, None].expand_as(sampled)
        if self.score == "features":
            cosine = F.cosine_similarity(sampled, values, dim=1)  # [B, M, P]
            total = weights.sum(-1).clamp_min(1e-9)
            score = (cosine * weights).sum(-1) / total
        else:
            score = trimmed_zncc(
                sampled[:, 0], values[:, 0], weights, self.trim_sigma, self.trim_passes
            )
        overlap = weights.sum(-1) / surface.valid.sum(-1, keepdim=True).clamp_min(1.0)
        return torch.where(
            overlap >= self.min_overlap, score, torch.full_like(score, NOT_SEEN_SCORE)
        )

    @torch.no_grad()
    def _score_rendered(self, poses: Tensor, level: Level) -> Tensor:
        """Scores [B, M] of candidate poses [B, M, 7] by rendering each candidate's image."""
        b, m = poses.shape[:2]
        _, c, h, w = level.target.shape
        rendering = self.scene_model.render(
            poses.reshape(b * m, 7),
            level.scenes.repeat_interleave(m),
            level.intrinsics.repeat_interleave(m, 0),
            w,
            h,
        )
        if self.score == "features":
            assert self.features is not None
            maps = self.features(rendering.rgb).view(b, m, c, h * w)
            target = level.target.flatten(2)[:, None]
            return F.cosine_similarity(maps, target, dim=2).mean(-1)
        rendered = band_pass(self._grey(rendering.rgb), *level.sigmas).view(b, m, h * w)
        target = level.target.view(b, 1, h * w).expand_as(rendered)
        return trimmed_zncc(
            target, rendered, torch.ones_like(rendered), self.trim_sigma, self.trim_passes
        )

    @torch.no_grad()
    def score_poses(self, poses: Tensor, level: Level, surface: Surface | None) -> Tensor:
        """Scores [B, M] of candidate poses [B, M, 7] at ``level``."""
        if surface is None:
            return self._score_rendered(poses, level)
        self.work.score_points += int(surface.valid.sum()) * poses.shape[1]
        with self.work.timed("score"):
            return self._score_surface(poses, level, surface)

    def _score_surface(self, poses: Tensor, level: Level, surface: Surface) -> Tensor:
        if self._compiled(poses.device):
            return compiled_zncc_scores(
                surface.points,
                surface.values[:, 0],
                surface.valid,
                poses,
                level.intrinsics,
                level.target[:, 0],
                self.min_overlap,
                self.trim_sigma,
                self.trim_passes,
            )
        return self._score_projected(poses, level, surface)

    @torch.no_grad()
    def search(
        self, initial: Tensor, level: Level, surface: Surface | None, draws: Tensor
    ) -> Hypotheses:
        """The sampling search from poses [B, 7] with draws [B, rounds, K·C, 6] -> K
        hypotheses per query (one, the start, without rounds)."""
        b, k, c = len(initial), self.hypotheses, self.candidates
        start = Hypotheses(initial[:, None], self.score_poses(initial[:, None], level, surface))
        if not self.rounds:
            return start
        sigma = initial.new_tensor(self.sigma)
        first = torch.cat([sigma[:1].expand(3), sigma[1:].expand(3)])  # [6]
        seeds = perturb(initial[:, None].expand(-1, k * c, -1), draws[:, 0] * first)
        scores = self.score_poses(seeds, level, surface)
        chains = Hypotheses(
            torch.cat([start.poses, seeds], 1), torch.cat([start.scores, scores], 1)
        ).top(k)
        chains.steps = first.expand(b, chains.scores.shape[1], 6).clone()
        k = chains.scores.shape[1]
        for round_index in range(1, self.rounds):
            steps = draws[:, round_index, : k * c].view(b, k, c, 6) * chains.steps[:, :, None]
            candidates = perturb(chains.poses[:, :, None].expand(-1, -1, c, -1), steps)
            scores = self.score_poses(candidates.view(b, k * c, 7), level, surface).view(b, k, c)
            top, pick = scores.max(-1)
            improved = top > chains.scores
            chosen = candidates.gather(2, pick[..., None, None].expand(-1, -1, 1, 7))[:, :, 0]
            chains.poses = torch.where(improved[..., None], chosen, chains.poses)
            chains.scores = torch.where(improved, top, chains.scores)
            chains.steps = torch.where(
                improved[..., None], chains.steps, chains.steps * self.shrink
            )
        return chains

    @torch.no_grad()
    def polish(self, hypotheses: Hypotheses, level: Level, surface: Surface) -> Hypotheses:
        """``polish_steps`` Levenberg–Marquardt steps on every hypothesis at ``level``."""
        if not self.polish_steps or self.score != "zncc":
            return hypotheses
        run = polish_compiled if self._compiled(hypotheses.poses.device) else polish_tensor
        hypothesis_count = hypotheses.scores.shape[1]
        self.work.polish_point_steps += (
            int(surface.valid.sum()) * hypothesis_count * self.polish_steps
        )
        with self.work.timed("polish"):
            problem = PolishProblem(
                surface.points,
                surface.values[:, 0],
                surface.valid,
                quaternion_to_matrix(hypotheses.poses[..., 3:]),
                hypotheses.poses[..., :3],
                hypotheses.scores,
                level.intrinsics,
                level.target[:, 0],
            )
            settings = PolishSettings(
                self.polish_steps,
                self.polish_damping,
                self.min_overlap,
                self.trim_sigma,
                self.trim_passes,
            )
            rotation, position, scores = run(problem, settings)
        dtype = hypotheses.poses.dtype
        quaternion = matrix_to_quaternion(rotation.to(dtype))
        return Hypotheses(torch.cat([position.to(dtype), quaternion], -1), scores.to(dtype))

    @torch.no_grad()
    def refine_chunk(
        self, images: Tensor, intrinsics: Tensor, initial: Tensor, scenes: Tensor, draws: Tensor
    ) -> RenderCompareResult:
        """Refine one chunk: search at the coarsest level, polish coarse to fine."""
        levels = self.pyramid(images, intrinsics, scenes)
        depth = self.scene_model.has_depth
        reference = None
        if depth:
            reference = self.reference(
                initial, levels[-1], self.reference_size, self.reference_fov_scale
            )

        def surface_at(level: Level) -> Surface | None:
            return self.surface(reference, level) if reference is not None else None

        surface = surface_at(levels[0])
        hypotheses = self.search(initial, levels[0], surface, draws)
        for index, level in enumerate(levels):
            last = index == len(levels) - 1
            if last and reference is not None and self.final_reference_size:
                best, _ = hypotheses.best()
                reference = self.reference(
                    best, level, self.final_reference_size, self.final_fov_scale
                )
            if index:
                surface = surface_at(level)
                hypotheses.scores = self.score_poses(hypotheses.poses, level, surface)
            if surface is not None:
                hypotheses = self.polish(hypotheses, level, surface)
            if not last:
                hypotheses = hypotheses.top(-(-hypotheses.scores.shape[1] // 2))
        best, score = hypotheses.best()
        initial_score = self.score_poses(initial[:, None], levels[-1], surface)[:, 0]
        return RenderCompareResult(best, score, initial_score)

    def __call__(
        self,
        images: Tensor,
        intrinsics: Tensor,
        initial: Tensor,
        scenes: Tensor,
        draws: Tensor | None = None,
        keys: Tensor | None = None,
    ) -> RenderCompareResult:
        """Refine queries: images [B, 3, H, W] RGB in [0, 1] with intrinsics [B, 4] (px of
        those images), initial poses [B, 7], scene ids [B]; draws as from :meth:`draws`, or
        ``keys`` [B] (:meth:`keyed_draws`: a query's result then does not depend on the
        batch), else made chunk by chunk from :meth:`draw_stream`."""
        initial = torch.cat([initial[:, :3], normalize_quaternion(initial[:, 3:])], -1).float()
        stream = self.draw_stream() if keys is None else self.keyed_draws
        parts = []
        chunk = self.chunk_for(initial.device)
        for rows in torch.arange(len(initial), device=initial.device).split(chunk):
            ask = len(rows) if keys is None else keys[rows.cpu()].cpu()
            chunk_draws = stream(ask) if draws is None else draws[rows.cpu()]
            with float32_arithmetic():
                parts.append(
                    self.refine_chunk(
                        images[rows].float(),
                        intrinsics[rows],
                        initial[rows],
                        scenes[rows],
                        chunk_draws.to(initial.device),
                    )
                )
        return RenderCompareResult(*(torch.cat(column) for column in zip(*parts, strict=True)))
