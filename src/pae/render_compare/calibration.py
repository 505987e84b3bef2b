"""What render-and-compare chooses on validation queries, with their true poses, and applies
at test: the acceptance gate (margin and score floor) and the search's first steps."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from pae.core.geometry import pose_errors
from pae.core.pose_sampling import perturb_poses
from pae.data.transforms import ImageTransform
from pae.render_compare.correspondences import MatchSettings
from pae.render_compare.gate import ACCEPT_ALL
from pae.render_compare.scene_decision import SceneRule

MARGIN_QUANTILES = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
"""Candidate acceptance margins besides accept-all and 0, and score floors besides none:
these quantiles of the validation queries' score gains and refined scores."""


@dataclasses.dataclass(frozen=True)
class Calibration:
    """The gate (``accept_margin``: a ZNCC gain; ``accept_score``: a ZNCC floor), the
    search's first steps and any other refiner setting chosen on val (``steps``:
    ``position_sigma_m``, ``orientation_sigma_deg``, ``highpass_sigma_px``,
    ``highpass_levels``, ``contrast_sigma_px``, ``surface_share`` or any other of
    ``FILTER_KEYS``; empty: the refiner's settings) and how a multi-scene query's scene is
    decided (``scene``:
    :class:`pae.render_compare.scene_decision.SceneRule`; by default no query is checked in
    the other scenes) and the correspondence stage (``match``:
    :class:`pae.render_compare.correspondences.MatchSettings`; by default off), applied to
    queries without true poses."""

    accept_margin: float = 0.0
    accept_score: float = ACCEPT_ALL
    steps: Mapping[str, float] = dataclasses.field(default_factory=dict)
    scene: SceneRule = dataclasses.field(default_factory=SceneRule)
    match: MatchSettings = dataclasses.field(default_factory=MatchSettings)


KEEP_ALL = 4.0
"""A margin above every possible score gain: every start kept (the refiner does not help)."""
OBJECTIVES = ("mean", "log_ratio")
RATIO_EPS_M = 1e-3
"""Added to both errors (m) of a ``log_ratio``: below a millimetre no start is improved."""
LADDER = (0.0025, 0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.32)
"""The error scales of :func:`ladder_starts`, as shares of the scene's size (the best APRs'
errors lie near 1 % of it: DFNet's 3 cm in a 3 m room, 70 cm on a 120 m street)."""
LADDER_DEG = (0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
"""Their orientation errors (deg), paired scale by scale."""
STEP_SHARES = (0.01, 0.02, 0.05, 0.1, 0.2)
"""Candidate first position steps of :func:`pae.render_compare.calibrate_any_start`, as
shares of the scene's size (orientation steps in proportion: LADDER_DEG / LADDER)."""
STAGE_SHARE_TOLERANCE = 0.02
"""How much :func:`pae.render_compare.calibrate_any_start` lets the val objective (the mean
log error ratio) rise when it gives the correspondence stage to fewer queries: 0.02, about
2 % on the geometric mean of the errors over their starts'."""
SURFACE_SHARES = (0.5, 0.6, 0.7, 0.8)
"""The references' surface shares (``surface_share``) that
:func:`pae.render_compare.calibrate_any_start` tries besides the settings' own: a fitted
volume keeps a faint fog in front of its surfaces (denser the fewer views saw a place), which
pulls the light's mean depth towards the camera; the depth by which a ray has gathered 50-80 %
of its opacity lies on the surface, the share that serves best differing from scene to scene
(experiments/render_compare_real_starts, "The surface depth")."""
HIGHPASS_PX = 4.0
"""The high-pass that :func:`pae.render_compare.calibrate_any_start` tries beside the
settings' own (``highpass_sigma_px``, px at the compare resolution), at every level and at
the finest only (``highpass_levels`` 0 and 1): it removes what varies slowly across the image
(shading, a light's hot spot, exposure) that a scene model fitted under other light cannot
explain, at the cost of the coarse levels' reach where it applies there too."""
CONTRAST_PX = (2.0,)
"""The local contrasts that :func:`pae.render_compare.calibrate_any_start` tries with each
high-pass (``contrast_sigma_px``, px at the compare resolution, besides none): the band-passed
images divided by their RMS within that σ, so that a region's texture counts alike whether a
light's hot spot, vignetting or exposure made it bright or dim there."""


def scene_size(train_positions: Tensor) -> float:
    """A scene's size (m) from its train camera positions [N, 3]: twice the 90th percentile
    of their distances to the median position."""
    centre = train_positions.median(0).values
    return 2 * float((train_positions - centre).norm(dim=-1).quantile(0.9))


def ladder_starts(truth: Tensor, size_m: float, generator: torch.Generator | None = None) -> Tensor:
    """Validation starts at every error scale an APR may bring: query i of true poses [N, 7]
    moved by about ``LADDER[i % K]`` x ``size_m`` (m) and ``LADDER_DEG[i % K]`` deg
    (:func:`pae.core.pose_sampling.perturb_poses`) -> [N, 7]."""
    k = torch.arange(len(truth)) % len(LADDER)
    position = torch.tensor(LADDER, dtype=torch.float64)[k] * size_m
    orientation = torch.tensor(LADDER_DEG, dtype=torch.float64)[k]
    return perturb_poses(truth.double(), position, orientation, generator).to(truth)


AUTO = "auto"


def _number_or_auto(key: str, value: float | str) -> float | None:
    if value == AUTO:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"render_compare.{key} must be a number or auto, not {value!r}")
    return float(value)


FILTER_KEYS = (
    "highpass_sigma_px",
    "highpass_levels",
    "contrast_sigma_px",
    "trim_sigma",
    "trim_passes",
    "blur_sigma_px",
    "highlight_quantile",
    "surface_share",
)
"""The refiner settings a filter tried on val may set: how the compared images are filtered
and scored, and where the references' surface points lie."""


def _check_matches(key: str, matches: Sequence[Mapping[str, Any]]) -> None:
    """Each of ``matches`` a valid :class:`MatchSettings` mapping; a ValueError naming the
    first unknown setting under ``key``."""
    known = {field.name for field in dataclasses.fields(MatchSettings)}
    for chosen in matches:
        unknown = sorted(set(chosen) - known)
        if unknown:
            raise ValueError(
                f"{key}: {unknown[0]} is not a match setting; choose among {sorted(known)}"
            )
        MatchSettings(**chosen)


def _check_shares(shares: Sequence[float]) -> None:
    """Each of ``shares`` in (0, 1); a ValueError naming the first outside."""
    outside = [share for share in shares if not 0 < share < 1]
    if outside:
        raise ValueError(
            f"render_compare.match_shares_from_val: {outside[0]} is not a share in (0, 1)"
        )


def _check_filters(key: str, filters: Sequence[Mapping[str, float]]) -> None:
    """Each of ``filters`` a mapping of ``FILTER_KEYS``; a ValueError naming the first
    unknown setting under ``key``."""
    for chosen in filters:
        unknown = sorted(set(chosen) - set(FILTER_KEYS))
        if unknown:
            raise ValueError(
                f"{key}: {unknown[0]} is not a filter setting; choose among {list(FILTER_KEYS)}"
            )


@dataclasses.dataclass(frozen=True)
class CalibrationOptions:
    """What :func:`pae.render_compare.calibrate` chooses on validation and what it keeps.

    - ``accept_margin``: a refined pose replaces the start only where its score beats the
      start's by more than this margin (a ZNCC difference); ``auto``: the margin that
      minimises the val queries' mean position error, applied at test.
    - ``accept_score``: and only where the refined score itself exceeds this floor (a ZNCC: a
      low final score marks a query the scene model does not explain); ``auto``: chosen with
      the margin; -4 (the default): no floor (scores lie in [-2, 1]).
    - ``step_from_val``: ``{"position": a, "orientation": b}``, the search's first steps as
      shares of the starts' median val errors (so that it covers them in a room and on a
      street alike); None: the refiner's own.
    - ``scene_check_below``: teachers that predict the scene: a query whose refined score in
      its predicted scene is below this ZNCC is refined in every other scene too and moved
      where the evidence beats its own by a margin, all chosen on val
      (:mod:`pae.render_compare.scene_decision`); ``auto``: the floor chosen too; -4: never,
      2: always.
    - ``filters_from_val``: image filters to try on val, each a mapping of ``FILTER_KEYS``
      (``{}``: the refiner's own; e.g. ``{"highpass_sigma_px": 4, "trim_sigma": 2.5}``);
      the one whose gated refinement minimises the ``gate_objective`` is kept. None: the
      refiner's own only.
    - ``matches_from_val``: correspondence stages to try on val with the chosen filter, each
      a mapping of :class:`pae.render_compare.correspondences.MatchSettings` (``{}``: none);
      the one whose gated refinement minimises the ``gate_objective`` is kept (a single one:
      used without validation too). None: none.
    - ``match_shares_from_val``: for another APR's starts only
      (:class:`AnyStartOptions`' ``stage_shares``): the shares of the val queries the
      stage kept may go to. None: as listed.
    - ``gate_objective``: the calibration's one objective over the val queries, which the
      filter, the correspondence stage and the automatic margin and floor
      (:func:`choose_gate`) all minimise: ``mean`` their mean position error, ``log_ratio``
      the mean log of each query's error over its start's (a few refinements that fly metres
      off then weigh no more than a few that halve their start's error).
    """

    accept_margin: float | str = AUTO
    accept_score: float | str = ACCEPT_ALL
    step_from_val: Mapping[str, float] | None = None
    scene_check_below: float | str = AUTO
    filters_from_val: Sequence[Mapping[str, float]] | None = None
    gate_objective: str = "mean"
    matches_from_val: Sequence[Mapping[str, Any]] | None = None
    match_shares_from_val: Sequence[float] | None = None

    def __post_init__(self) -> None:
        if self.gate_objective not in OBJECTIVES:
            raise ValueError(
                f"render_compare.gate_objective: unknown {self.gate_objective!r}; choose one "
                f"of {list(OBJECTIVES)}"
            )
        for key in ("accept_margin", "accept_score", "scene_check_below"):
            _number_or_auto(key, getattr(self, key))
        steps = self.step_from_val
        if steps is not None and (
            set(steps) != {"position", "orientation"} or min(steps.values()) <= 0
        ):
            raise ValueError(
                "render_compare.step_from_val needs position and orientation fractions > 0, "
                f"got {dict(steps)!r}"
            )
        _check_filters("render_compare.filters_from_val", self.filters_from_val or ())
        _check_matches("render_compare.matches_from_val", self.matches_from_val or ())
        _check_shares(self.match_shares_from_val or ())

    def fixed(self, key: str) -> float | None:
        """The option ``key`` as a number, None where it is ``auto``."""
        return _number_or_auto(key, getattr(self, key))

    def uncalibrated(self) -> Calibration:
        """The calibration where no validation ran: the fixed options, else margin 0, no
        floor, the refiner's steps and no scene check (a fixed check floor: the refined
        score decides, without prior or margin)."""
        margin, floor = self.fixed("accept_margin"), self.fixed("accept_score")
        below = self.fixed("scene_check_below")
        matches = self.matches_from_val or ()
        return Calibration(
            0.0 if margin is None else margin,
            ACCEPT_ALL if floor is None else floor,
            {},
            SceneRule(ACCEPT_ALL if below is None else below),
            MatchSettings(**matches[0]) if len(matches) == 1 else MatchSettings(),
        )


@dataclasses.dataclass(frozen=True)
class AnyStartOptions:
    """What :func:`pae.render_compare.calibrate_any_start` tries on validation besides the
    settings' own: the high-passes ``highpass_px`` (px at the compare resolution, at every
    level and at the finest only), the local contrasts ``contrast_px`` (px, with each
    high-pass, besides none), the further ``filters`` (mappings of ``FILTER_KEYS``, as
    ``render_compare.filters_from_val`` lists them: a highlight clip, a trimmed score), the
    references' ``surface_shares`` and, where the queries carry ``matching``, the
    correspondence stages ``matches`` (mappings of
    :class:`pae.render_compare.correspondences.MatchSettings`; none is always tried too)
    and, where one is kept, the ``stage_shares`` of the val queries, the lowest-scoring
    first, to give it to instead of those its own ``below_score`` picks (every query by
    default; each share in (0, 1): the smallest whose objective stays within
    ``STAGE_SHARE_TOLERANCE`` of the stage's own is kept, its score threshold as the
    stage's ``below_score``); ``seed``: the ladder starts' draws
    (:func:`ladder_starts`)."""

    highpass_px: Sequence[float] = (HIGHPASS_PX,)
    contrast_px: Sequence[float] = CONTRAST_PX
    surface_shares: Sequence[float] = SURFACE_SHARES
    seed: int = 0
    matches: Sequence[Mapping[str, Any]] = ()
    filters: Sequence[Mapping[str, float]] = ()
    stage_shares: Sequence[float] = ()

    def __post_init__(self) -> None:
        _check_matches("render_compare.matches_from_val", self.matches)
        _check_filters("render_compare.filters_from_val", self.filters)
        _check_shares(self.stage_shares)

    def stages(self) -> list[MatchSettings]:
        """The correspondence stages to try: none first, then each of ``matches`` once."""
        stages = [MatchSettings(), *(MatchSettings(**chosen) for chosen in self.matches)]
        return list(dict.fromkeys(stages))


def objective_value(poses: Tensor, starts: Tensor, truth: Tensor, objective: str) -> float:
    """The calibration's ``objective`` over refined poses [N, 7] from starts [N, 7] with true
    poses [N, 7]: ``mean`` the mean position error (m), ``log_ratio`` the mean log of each
    query's position error over its start's."""
    refined, _ = pose_errors(poses.float(), truth.float())
    if objective == "mean":
        return float(refined.mean())
    start, _ = pose_errors(starts.float(), truth.float())
    return float(((refined + RATIO_EPS_M) / (start + RATIO_EPS_M)).log().mean())


def choose_gate(
    gains: Tensor,
    scores: Tensor,
    refined_error: Tensor,
    start_error: Tensor,
    margin: float | None = None,
    floor: float | None = None,
    objective: str = "mean",
) -> tuple[float, float]:
    """The acceptance margin and score floor that minimise the ``objective`` over queries
    with score gains [N] (refined minus start), refined scores [N] and position errors [N]
    (m) of the refined poses and of the starts: ``mean`` the mean position error, ``log_ratio``
    the mean log of each query's error over its start's (every start scale counts alike: a
    good start made worse costs as much as a bad one made better gains). Margins: accept-all
    (``ACCEPT_ALL``), 0, keep every start (``KEEP_ALL``) and ``MARGIN_QUANTILES`` of the
    gains; floors: none (``ACCEPT_ALL``) and those quantiles of the refined scores; a given
    ``margin`` or ``floor`` is kept as it is. The smallest margin, then the smallest floor,
    wins ties."""
    if not len(gains):
        return (0.0 if margin is None else margin), (ACCEPT_ALL if floor is None else floor)
    levels = gains.new_tensor(MARGIN_QUANTILES, dtype=torch.float)

    def candidates(values: Tensor, fixed: float | None, base: list[float]) -> Tensor:
        if fixed is not None:
            return torch.tensor([float(fixed)])
        grid = torch.cat([torch.tensor(base), values.float().quantile(levels)])
        return grid.sort().values

    margins = candidates(gains, margin, [ACCEPT_ALL, 0.0, KEEP_ALL])
    floors = candidates(scores, floor, [ACCEPT_ALL])
    accepted = (gains.float() > margins[:, None, None]) & (scores.float() > floors[None, :, None])
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown gate objective {objective!r}; choose one of {OBJECTIVES}")
    if objective == "log_ratio":
        ratio = (refined_error.float() + RATIO_EPS_M) / (start_error.float() + RATIO_EPS_M)
        refined_error, start_error = ratio.log(), torch.zeros_like(ratio)
    errors = torch.where(accepted, refined_error, start_error).mean(-1)  # [K, F]
    best = int(errors.flatten().argmin())
    return float(margins[best // len(floors)]), float(floors[best % len(floors)])


def steps_from_errors(
    estimate: Tensor, truth: Tensor, fractions: Mapping[str, float]
) -> dict[str, float]:
    """The search's first steps from the starts' median errors: estimates [N, 7] against
    their true poses [N, 7]; ``fractions``: ``position`` and ``orientation``, the steps as
    shares of the median position (m) and orientation (deg) errors."""
    pos, rot = pose_errors(estimate.float(), truth.float())
    return {
        "position_sigma_m": float(fractions["position"] * pos.quantile(0.5)),
        "orientation_sigma_deg": float(fractions["orientation"] * rot.quantile(0.5)),
    }


def teacher_features(teacher: torch.nn.Module, layers: int) -> Any:
    """The first ``layers`` modules of the teacher backbone's feature extractor, applied to
    RGB images in [0, 1] (normalised as the teacher's inputs are)."""
    features = teacher.backbone.features[:layers]

    def extract(rgb: Tensor) -> Tensor:
        return features(ImageTransform.normalize_batch(rgb))

    return extract
