"""Render-and-compare pose refinement against a scene model learned from the train images.

Starting from the teacher's estimate, a sampling search moves each query's pose (position
and orientation): every round draws ``candidates`` 6-DoF perturbations around the best pose
so far, scores them by how well the scene model rendered there matches the query image, keeps
the best and shrinks the steps of queries that found nothing better. Optional gradient steps
then polish the pose through the differentiable projection.

Scores are appearance-invariant: the zero-mean normalised cross-correlation (ZNCC) of blurred
grey images, or (``score="features"``) the mean cosine similarity of feature maps of a
given extractor (the teacher's backbone). A model with depth is rendered once per query (at
the best pose, with a wider field of view) and its surface points are projected into each
candidate camera; a model without depth renders every candidate's image.

Every query of a call is refined at once, in chunks of ``chunk`` queries: no Python loop runs
per query. The random draws come from one generator in query order (``draws``), so a query's
result does not depend on the batch it is refined in.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from pae.data.camera import camera_rays, project, scale_intrinsics
from pae.geometry import normalize_quaternion, quaternion_to_matrix
from pae.models.scene_model import SceneModel
from pae.pose_sampling import perturb
from pae.refine.render_score import MIN_DEPTH_M, NOT_SEEN_SCORE, compiled_zncc_scores

SCORES = ("zncc", "features")
ENGINES = ("auto", "compiled", "torch")
"""auto: the compiled ZNCC scorer for CPU tensors (``pae.refine.render_score``), tensor
operations otherwise; compiled: always (ZNCC only); torch: always tensor operations."""
FeatureExtractor = Callable[[Tensor], Tensor]
"""RGB images [B, 3, H, W] in [0, 1] -> feature maps [B, C, h, w]."""


class RenderCompareResult(NamedTuple):
    """poses [B, 7] refined; score [B] of the refined pose; initial_score [B] of the start."""

    poses: Tensor
    score: Tensor
    initial_score: Tensor


def grey(images: Tensor) -> Tensor:
    """RGB [B, 3, H, W] -> luma [B, 1, H, W] (ITU-R 601)."""
    weights = images.new_tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)
    return (images * weights).sum(1, keepdim=True)


def gaussian_blur(images: Tensor, sigma_px: float) -> Tensor:
    """Separable Gaussian blur of [B, C, H, W] (σ in px; 0: unchanged), edges replicated."""
    if sigma_px <= 0:
        return images
    radius = max(1, math.ceil(3 * sigma_px))
    x = torch.arange(-radius, radius + 1, dtype=images.dtype, device=images.device)
    kernel = torch.exp(-0.5 * (x / sigma_px) ** 2)
    kernel = kernel / kernel.sum()
    c = images.shape[1]
    padded = F.pad(images, (radius, radius, radius, radius), mode="replicate")
    rows = F.conv2d(padded, kernel.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(rows, kernel.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def zncc(a: Tensor, b: Tensor, weights: Tensor) -> Tensor:
    """Weighted zero-mean normalised cross-correlation over the last dimension of a, b
    [..., P] with weights [..., P] >= 0 -> [...] in [-1, 1] (0 where a side is flat)."""
    total = weights.sum(-1, keepdim=True).clamp_min(1e-9)
    a = a - (weights * a).sum(-1, keepdim=True) / total
    b = b - (weights * b).sum(-1, keepdim=True) / total
    cov = (weights * a * b).sum(-1)
    var = (weights * a * a).sum(-1) * (weights * b * b).sum(-1)
    return cov / var.clamp_min(1e-12).sqrt()


def trimmed_zncc(
    a: Tensor, b: Tensor, weights: Tensor, trim_sigma: float, passes: int = 2
) -> Tensor:
    """ZNCC [...] of a, b [..., P] over the points the fit explains: ``passes`` times, after
    a weighted least-squares fit ``a ≈ gain·b + offset`` on the points kept so far, the
    points whose residual exceeds ``trim_sigma`` residual standard deviations (an occluder, a
    highlight) are dropped (of all points, so a point may come back). ``trim_sigma <= 0``:
    plain :func:`zncc`. The selection is not differentiated; the score is, through the kept
    points."""
    if trim_sigma <= 0 or passes < 1:
        return zncc(a, b, weights)
    kept = weights
    with torch.no_grad():
        for _ in range(passes):
            total = kept.sum(-1, keepdim=True).clamp_min(1e-9)
            mean_a = (kept * a).sum(-1, keepdim=True) / total
            mean_b = (kept * b).sum(-1, keepdim=True) / total
            cov = (kept * (a - mean_a) * (b - mean_b)).sum(-1, keepdim=True)
            var_a = (kept * (a - mean_a).square()).sum(-1, keepdim=True)
            var_b = (kept * (b - mean_b).square()).sum(-1, keepdim=True)
            gain = cov / var_b.clamp_min(1e-12)
            sigma = ((var_a - gain * cov).clamp_min(0) / total).sqrt()
            residual = (a - mean_a) - gain * (b - mean_b)
            kept = weights * (residual.abs() <= trim_sigma * sigma).to(weights.dtype)
    return zncc(a, b, kept)


def compare_size(height: int, width: int, compare_width: int) -> tuple[int, int]:
    """The (height, width) in px at which a query of ``height × width`` px is compared."""
    return max(4, round(height * compare_width / width)), compare_width


class GatedPoses(NamedTuple):
    """poses [B, 7]: the refined pose where accepted, else the start; accepted [B] bool."""

    poses: Tensor
    accepted: Tensor


ACCEPT_ALL = -4.0
"""A margin (floor) below every possible score gain (score; scores lie in [-2, 1]): every
refinement kept."""


def gate(
    result: RenderCompareResult, initial: Tensor, margin: float, floor: float = ACCEPT_ALL
) -> GatedPoses:
    """Keep a refined pose only where its score beats the start's by more than ``margin``
    (a ZNCC difference; below -3 accepts every refinement) and itself exceeds ``floor`` (a
    ZNCC; below -2 accepts any) -> :class:`GatedPoses`."""
    accepted = (result.score - result.initial_score > margin) & (result.score > floor)
    start = initial.to(result.poses)
    return GatedPoses(torch.where(accepted[:, None], result.poses, start), accepted)


class _Queries(NamedTuple):
    """One chunk of queries prepared for scoring."""

    target: Tensor  # [B, C, h, w] blurred grey query (or its feature maps)
    intrinsics: Tensor  # [B, 4] of the compare resolution
    scenes: Tensor  # [B]


class _Surface(NamedTuple):
    """A model's surface seen from the reference cameras of a chunk."""

    points: Tensor  # [B, P, 3] world
    values: Tensor  # [B, C, P] grey (or features) of the rendering at those points
    valid: Tensor  # [B, P] float: the model explains that pixel


def band_pass(images: Tensor, sigma_px: float, highpass_sigma_px: float) -> Tensor:
    """[B, C, H, W] blurred at ``sigma_px`` minus, when ``highpass_sigma_px`` > 0, its blur at
    that wider σ (a difference of Gaussians: smooth shading and light fall-off removed)."""
    blurred = gaussian_blur(images, sigma_px)
    if highpass_sigma_px <= 0:
        return blurred
    return blurred - gaussian_blur(images, highpass_sigma_px)


class RenderCompareRefiner:
    """Render-and-compare refinement of APR estimates against ``scene_model``.

    rounds, candidates: the sampling search (candidate 0 of every round is the best pose so
    far); position_sigma_m, orientation_sigma_deg: the first round's step sizes (standard
    deviations per axis); shrink: the factor on a query's steps after a round without
    improvement; resolution: the compare images' width in px; blur_sigma_px: at that width;
    highpass_sigma_px: at that width, the blur subtracted from the compared images (0: none;
    see :func:`band_pass`); reference_size, reference_fov_scale: the reference rendering's
    width in px and its field of view relative to the query's; refresh_every: rounds between
    reference renderings at the current best pose (0: one rendering, at the start);
    min_overlap: the share of reference points a candidate must see, else it scores
    ``NOT_SEEN_SCORE`` (-2); trim_sigma, trim_passes: the ZNCC's robustness
    (:func:`trimmed_zncc`; trim_sigma 0: plain ZNCC); gradient_steps, gradient_lr,
    gradient_position_scale: Adam steps on the pose after the search (rotation in rad,
    translation in units of gradient_position_scale m: a scene k times larger moves k times
    further); score: ``zncc`` or ``features`` (needs ``features``); chunk: queries scored at
    once; engine: see ``ENGINES``.
    """

    def __init__(
        self,
        scene_model: SceneModel,
        rounds: int = 14,
        candidates: int = 32,
        position_sigma_m: float = 0.25,
        orientation_sigma_deg: float = 4.0,
        shrink: float = 0.6,
        resolution: int = 32,
        blur_sigma_px: float = 1.0,
        highpass_sigma_px: float = 0.0,
        reference_size: int = 24,
        reference_fov_scale: float = 1.3,
        refresh_every: int = 0,
        min_overlap: float = 0.4,
        trim_sigma: float = 0.0,
        trim_passes: int = 2,
        gradient_steps: int = 100,
        gradient_lr: float = 0.02,
        gradient_position_scale: float = 1.0,
        score: str = "zncc",
        features: FeatureExtractor | None = None,
        seed: int = 0,
        chunk: int = 64,
        engine: str = "auto",
    ) -> None:
        if score not in SCORES:
            raise ValueError(f"unknown render_compare.score {score!r}; choose one of {SCORES}")
        if engine not in ENGINES:
            raise ValueError(f"unknown render_compare.engine {engine!r}; choose one of {ENGINES}")
        if engine == "compiled" and score != "zncc":
            raise ValueError("render_compare.engine=compiled scores zncc only; use auto or torch")
        if score == "features" and gradient_steps:
            raise ValueError(
                "render_compare.gradient_steps polish the zncc score only; set "
                "render_compare.refiner.gradient_steps=0 with score=features"
            )
        if score == "features" and features is None:
            raise ValueError("render_compare.score=features needs a feature extractor")
        if rounds < 0 or candidates < 1 or resolution < 4 or reference_size < 4:
            raise ValueError(
                "render_compare needs rounds >= 0, candidates >= 1, resolution >= 4 and "
                "reference_size >= 4"
            )
        if highpass_sigma_px < 0:
            raise ValueError(
                f"render_compare needs highpass_sigma_px >= 0, not {highpass_sigma_px:g}"
            )
        if trim_sigma < 0 or trim_passes < 0:
            raise ValueError(
                f"render_compare needs trim_sigma >= 0 and trim_passes >= 0, not {trim_sigma} "
                f"and {trim_passes}"
            )
        self.scene_model = scene_model
        self.rounds = rounds
        self.candidates = candidates
        self.sigma = (position_sigma_m, math.radians(orientation_sigma_deg))
        self.shrink = shrink
        self.resolution = resolution
        self.blur_sigma_px = blur_sigma_px
        self.highpass_sigma_px = highpass_sigma_px
        self.reference_size = reference_size
        self.reference_fov_scale = reference_fov_scale
        self.refresh_every = refresh_every
        self.min_overlap = min_overlap
        self.trim_sigma = trim_sigma
        self.trim_passes = trim_passes
        self.gradient_steps = gradient_steps
        self.gradient_lr = gradient_lr
        self.gradient_position_scale = gradient_position_scale
        self.score = score
        self.features = features
        self.seed = seed
        self.chunk = chunk
        self.engine = engine

    def draw_stream(self) -> Callable[[int], Tensor]:
        """The search's standard-normal draws, made as they are needed: each call ``(n)``
        returns the next ``n`` queries' draws [n, rounds, candidates, 6] from the refiner's
        seed. Each query's share of the stream is padded to whole blocks of 16 numbers, the
        unit of torch's CPU normal sampler, so a sequence of calls yields exactly the draws
        of one call for all queries (tested): results never depend on the chunking."""
        generator = torch.Generator().manual_seed(self.seed)
        count = self.rounds * self.candidates * 6
        padded = -(-count // 16) * 16
        shape = (self.rounds, self.candidates, 6)

        def next_draws(n_queries: int) -> Tensor:
            numbers = torch.randn((n_queries, padded), generator=generator)
            return numbers[:, :count].reshape(n_queries, *shape)

        return next_draws

    def draws(self, n_queries: int, device: torch.device | str = "cpu") -> Tensor:
        """The first ``n_queries`` queries' draws of :meth:`draw_stream`, in query order."""
        return self.draw_stream()(n_queries).to(device)

    @torch.no_grad()
    def prepare_queries(self, images: Tensor, intrinsics: Tensor, scenes: Tensor) -> _Queries:
        """Query images [B, 3, H, W] (RGB in [0, 1]) with intrinsics [B, 4] -> what the
        score compares against, at the compare resolution."""
        h, w = images.shape[-2:]
        height, width = compare_size(h, w, self.resolution)
        small = F.interpolate(images, size=(height, width), mode="area")
        scaled = scale_intrinsics(intrinsics, width / w, height / h)
        if self.score == "features":
            assert self.features is not None
            maps = self.features(small)
            fh, fw = maps.shape[-2:]
            return _Queries(maps, scale_intrinsics(scaled, fw / width, fh / height), scenes)
        target = band_pass(grey(small), self.blur_sigma_px, self.highpass_sigma_px)
        return _Queries(target, scaled, scenes)

    def _reference_intrinsics(self, queries: _Queries) -> tuple[Tensor, int, int]:
        """Intrinsics [B, 4] of the reference renderings (a wider view centred like the
        query's), their width and height in px."""
        _, _, h, w = queries.target.shape
        width = self.reference_size
        height = max(4, round(h * width / w))
        scale = width / w / self.reference_fov_scale
        fx, fy, _, _ = queries.intrinsics.unbind(-1)
        centre_x = torch.full_like(fx, (width - 1) / 2)
        centre_y = torch.full_like(fy, (height - 1) / 2)
        return torch.stack([fx * scale, fy * scale, centre_x, centre_y], -1), width, height

    @torch.no_grad()
    def surface(self, poses: Tensor, queries: _Queries) -> _Surface:
        """Render the scene model at poses [B, 7] with the reference camera: its surface
        points, their grey values (or features) and where the model explains the image."""
        intrinsics, width, height = self._reference_intrinsics(queries)
        rendering = self.scene_model.render(poses, queries.scenes, intrinsics, width, height)
        assert rendering.depth is not None and rendering.opacity is not None
        origins, directions = camera_rays(poses, intrinsics, width, height)
        points = origins + rendering.depth.flatten(1)[..., None] * directions
        if self.score == "features":
            assert self.features is not None
            maps = self.features(rendering.rgb)
            values = F.interpolate(maps, size=(height, width), mode="bilinear").flatten(2)
        else:
            target_fx = queries.intrinsics[:, 0]
            scale = float((intrinsics[:, 0] / target_fx).mean())
            sigmas = (self.blur_sigma_px * scale, self.highpass_sigma_px * scale)
            values = band_pass(grey(rendering.rgb), *sigmas).flatten(2)
        valid = (rendering.opacity.flatten(1) > 0.5).to(points.dtype)
        return _Surface(points, values, valid)

    def _score_projected(self, poses: Tensor, queries: _Queries, surface: _Surface) -> Tensor:
        """Scores [B, M] of candidate poses [B, M, 7]: the surface projected into each
        candidate camera, compared with the query where it lands inside the image."""
        b, m = poses.shape[:2]
        rotation = quaternion_to_matrix(poses[..., 3:])  # [B, M, 3, 3]
        relative = surface.points[:, None] - poses[..., None, :3]  # [B, M, P, 3]
        local = torch.einsum("bmji,bmpj->bmpi", rotation, relative)
        h, w = queries.target.shape[-2:]
        uv = project(local, queries.intrinsics[:, None, None])
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
            queries.target, grid.view(b, m, -1, 2), align_corners=True, padding_mode="border"
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
    def _score_rendered(self, poses: Tensor, queries: _Queries) -> Tensor:
        """Scores [B, M] of candidate poses [B, M, 7] by rendering each candidate's image."""
        b, m = poses.shape[:2]
        _, c, h, w = queries.target.shape
        rendering = self.scene_model.render(
            poses.reshape(b * m, 7),
            queries.scenes.repeat_interleave(m),
            queries.intrinsics.repeat_interleave(m, 0),
            w,
            h,
        )
        if self.score == "features":
            assert self.features is not None
            maps = self.features(rendering.rgb).view(b, m, c, h * w)
            target = queries.target.flatten(2)[:, None]
            return F.cosine_similarity(maps, target, dim=2).mean(-1)
        rendered = band_pass(grey(rendering.rgb), self.blur_sigma_px, self.highpass_sigma_px)
        rendered = rendered.view(b, m, h * w)
        target = queries.target.view(b, 1, h * w).expand_as(rendered)
        return trimmed_zncc(
            target, rendered, torch.ones_like(rendered), self.trim_sigma, self.trim_passes
        )

    def _score(self, poses: Tensor, queries: _Queries, surface: _Surface | None) -> Tensor:
        if surface is None:
            return self._score_rendered(poses, queries)
        if self.engine == "compiled" or (
            self.engine == "auto" and self.score == "zncc" and poses.device.type == "cpu"
        ):
            return compiled_zncc_scores(
                surface.points,
                surface.values[:, 0],
                surface.valid,
                quaternion_to_matrix(poses[..., 3:]),
                poses[..., :3],
                queries.intrinsics,
                queries.target[:, 0],
                self.min_overlap,
                self.trim_sigma,
                self.trim_passes,
            )
        return self._score_projected(poses, queries, surface)

    def _surface_or_none(self, poses: Tensor, queries: _Queries) -> _Surface | None:
        return self.surface(poses, queries) if self.scene_model.has_depth else None

    @torch.no_grad()
    def _search(self, initial: Tensor, queries: _Queries, draws: Tensor) -> tuple[Tensor, ...]:
        """The sampling search for one chunk -> (best poses [B, 7], their scores [B], the
        initial scores [B], the last reference surface)."""
        best = initial
        surface = self._surface_or_none(best, queries)
        best_score = self._score(best[:, None], queries, surface)[:, 0]
        initial_score = best_score
        sigma = initial.new_tensor(self.sigma).repeat(len(initial), 1)  # [B, 2]
        scale = torch.cat([sigma[:, :1].expand(-1, 3), sigma[:, 1:].expand(-1, 3)], 1)
        for round_index in range(self.rounds):
            if self.refresh_every and round_index and round_index % self.refresh_every == 0:
                surface = self._surface_or_none(best, queries)
                best_score = self._score(best[:, None], queries, surface)[:, 0]
            steps = draws[:, round_index] * scale[:, None]
            steps[:, 0] = 0.0  # candidate 0: the best pose so far
            candidates = perturb(best[:, None].expand(-1, self.candidates, -1), steps)
            scores = self._score(candidates, queries, surface)
            top, pick = scores.max(1)
            improved = top > best_score
            chosen = candidates[torch.arange(len(best)), pick]
            best = torch.where(improved[:, None], chosen, best)
            best_score = torch.where(improved, top, best_score)
            scale = torch.where(improved[:, None], scale, scale * self.shrink)
        return best, best_score, initial_score, surface

    def _polish(
        self, poses: Tensor, scores: Tensor, queries: _Queries, surface: _Surface | None
    ) -> tuple[Tensor, Tensor]:
        """Adam steps on a 6-DoF increment of each pose, maximising the projected score; a
        query keeps its pose where they do not raise its score -> (poses, scores)."""
        if not self.gradient_steps or surface is None:
            return poses, scores
        # evaluation loops run in inference mode: these steps need autograd, on copies
        with torch.inference_mode(False), torch.enable_grad():
            poses, queries, surface = (
                poses.clone(),
                _Queries(*(t.clone() for t in queries)),
                _Surface(*(t.clone() for t in surface)),
            )
            increment = torch.zeros(len(poses), 6, dtype=poses.dtype, requires_grad=True)
            optimiser = torch.optim.Adam([increment], lr=self.gradient_lr)
            units = poses.new_tensor([self.gradient_position_scale] * 3 + [1.0] * 3)
            for _ in range(self.gradient_steps):
                moved = perturb(poses, increment * units)
                loss = -self._score_projected(moved[:, None], queries, surface).sum()
                optimiser.zero_grad()
                loss.backward()
                optimiser.step()
        with torch.no_grad():
            polished = perturb(poses, increment.detach() * units)
            after = self._score(polished[:, None], queries, surface)[:, 0]
        better = after > scores
        return torch.where(better[:, None], polished, poses), torch.where(better, after, scores)

    def __call__(
        self,
        images: Tensor,
        intrinsics: Tensor,
        initial: Tensor,
        scenes: Tensor,
        draws: Tensor | None = None,
    ) -> RenderCompareResult:
        """Refine queries: images [B, 3, H, W] RGB in [0, 1] with intrinsics [B, 4] (px of
        those images), initial poses [B, 7], scene ids [B]; draws as from :meth:`draws`
        (None: made chunk by chunk from :meth:`draw_stream`)."""
        initial = torch.cat([initial[:, :3], normalize_quaternion(initial[:, 3:])], -1).float()
        stream = self.draw_stream()
        poses, scores, initial_scores = [], [], []
        for rows in torch.arange(len(initial), device=initial.device).split(self.chunk):
            chunk_draws = stream(len(rows)) if draws is None else draws[rows.cpu()]
            queries = self.prepare_queries(images[rows].float(), intrinsics[rows], scenes[rows])
            best, score, start, surface = self._search(
                initial[rows], queries, chunk_draws.to(initial.device)
            )
            best, score = self._polish(best, score, queries, surface)
            poses.append(best)
            scores.append(score)
            initial_scores.append(start)
        return RenderCompareResult(torch.cat(poses), torch.cat(scores), torch.cat(initial_scores))
