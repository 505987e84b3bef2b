"""The correspondence stage: keypoint matches against the scene model's renderings and the
train views, lifted through its depth, the pose solved by PnP; the train views' poses as
starts of their own; how refine() and calibrate() use both."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from pae.core.camera import project
from pae.core.geometry import pose_errors, quaternion_to_matrix
from pae.core.pose_sampling import perturb
from pae.render_compare import (
    Calibration,
    CalibrationOptions,
    Queries,
    Validation,
    calibrate,
    refine,
)
from pae.render_compare.correspondences import (
    Keypoints,
    MatchQueries,
    MatchSettings,
    TrainImages,
    correspond,
    lift,
    mutual_matches,
)
from pae.render_compare.refiner import RenderCompareRefiner
from pae.scene_model.oracle import OracleSceneModel
from pae.synthetic import (
    Appearance,
    PinholeCamera,
    SyntheticSettings,
    make_scene,
    make_sequences,
    render_batch,
)

SMALL_SEARCH = {"rounds": 2, "candidates": 6, "resolution": 24, "reference_size": 16}


def _frames(size: int, rows: slice) -> tuple[OracleSceneModel, torch.Tensor, ...]:
    """Frames ``rows`` of benchmark scene 0's last walk at ``size`` px: the oracle, images
    [N, 3, size, size] in [0, 1], intrinsics [N, 4] and true poses [N, 7]."""
    scene, camera = make_scene(0), PinholeCamera(size)
    walks = make_sequences(0, scene, SyntheticSettings(train_frames=6, test_frames=120))
    poses = walks[-1].poses[rows]
    images = render_batch(scene, poses, camera, Appearance(), supersample=1)
    f, c = camera.focal_px, camera.principal_point
    return (
        OracleSceneModel([scene]),
        torch.from_numpy(images).float().div(255).permute(0, 3, 1, 2),
        torch.tensor([f, f, c, c]).expand(len(poses), 4).clone(),
        torch.from_numpy(poses).float(),
    )


def test_mutual_matches_keep_the_mutual_unambiguous_nearest_neighbours() -> None:
    reference = torch.eye(6)[None]  # six distinct descriptors
    order = torch.tensor([3, 0, 5, 1, 4, 2])
    query = reference[:, order].clone()
    query[0, 5] = (reference[0, 2] + reference[0, 4]) / 2  # halfway between two: ambiguous
    count = torch.tensor([6])
    index, matched = mutual_matches(
        Keypoints(torch.zeros(1, 6, 2), query, count),
        Keypoints(torch.zeros(1, 6, 2), reference, count),
        ratio=0.8,
        binary=False,
    )
    assert matched[0, :5].all() and not matched[0, 5]
    assert torch.equal(index[0, :5], order[:5])
    short = Keypoints(torch.zeros(1, 6, 2), reference, torch.tensor([4]))  # 2 are padding
    query_keypoints = Keypoints(torch.zeros(1, 6, 2), query, count)
    index, matched = mutual_matches(query_keypoints, short, 0.8, False)
    # without reference 4 the halfway descriptor is no longer ambiguous: it matches 2
    assert index[matched].tolist() == [3, 0, 1, 2]


def test_lift_puts_a_pixel_at_its_depth_along_its_ray() -> None:
    pose = torch.tensor([[0.3, -0.2, 1.0, 0.9, 0.1, 0.3, -0.2]])
    pose[:, 3:] = pose[:, 3:] / pose[:, 3:].norm()
    intrinsics = torch.tensor([[40.0, 40.0, 15.5, 11.5]])
    depth = torch.full((1, 24, 32), 2.5)
    opacity = torch.ones(1, 24, 32)
    opacity[0, 0, 0] = 0.0  # the model sees nothing at the top-left pixel
    xy = torch.tensor([[[7.0, 5.0], [0.0, 0.0]]])
    world, seen = lift(xy, depth, opacity, pose, intrinsics)
    assert seen.tolist() == [[True, False]]
    local = torch.einsum("ij,kj->ki", quaternion_to_matrix(pose[0, 3:]).T, world[0] - pose[0, :3])
    torch.testing.assert_close(local[0, 2], torch.tensor(2.5))
    torch.testing.assert_close(project(local[:1], intrinsics[0]), xy[0, :1])


def test_correspondences_solve_the_pose_far_beyond_a_photometric_basin() -> None:
    """Starts 0.45 m and about 14 degrees off; keypoints on the query matched against the
    oracle's rendering at the start give the pose within a few centimetres; a blank image
    finds nothing and keeps its start."""
    model, images, intrinsics, truth = _frames(128, slice(0, 48, 12))
    offset = torch.tensor([0.3, -0.25, 0.2, 0.15, -0.15, 0.1])
    starts = perturb(truth, offset.expand(len(truth), 6))
    scenes = torch.zeros(len(truth), dtype=torch.long)
    settings = MatchSettings(width=128, render_width=128, min_inliers=10)
    images[-1] = 0.5
    found = correspond(model, images, intrinsics, starts, scenes, settings)
    position, orientation = pose_errors(found.poses, truth)
    start_position, _ = pose_errors(starts, truth)
    assert float(start_position.min()) > 0.4
    assert found.found[:-1].all() and not found.found[-1]
    assert float(position[found.found].max()) < 0.05 and float(orientation[found.found].max()) < 1
    torch.testing.assert_close(found.poses[~found.found], starts[~found.found])


def test_correspondences_do_not_depend_on_how_the_queries_are_chunked() -> None:
    """Two render-match-solve rounds over queries whose poses move by different amounts:
    matched two at a time, the poses, inliers and matches are those matched all at once."""
    model, images, intrinsics, truth = _frames(96, slice(0, 60, 12))
    offsets = torch.tensor([0.3, -0.25, 0.2, 0.15, -0.15, 0.1]) * torch.linspace(0, 1, 5)[:, None]
    starts = perturb(truth, offsets)
    scenes = torch.zeros(len(truth), dtype=torch.long)
    settings = MatchSettings(width=96, render_width=96, min_inliers=10, iterations=2)
    whole = correspond(model, images, intrinsics, starts, scenes, settings)
    chunked = correspond(model, images, intrinsics, starts, scenes, settings, chunk=2)
    assert whole.found.sum() >= 3
    with pytest.raises(ValueError, match="chunk must be >= 1 query, not 0"):
        correspond(model, images, intrinsics, starts, scenes, settings, chunk=0)
    for a, b in zip(whole, chunked, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)


def test_train_views_nearest_in_appearance_become_starts_of_their_own() -> None:
    """A query whose start is 1.5 m off, beyond the search; the train views include a frame
    next to it on the walk: refined from that view's pose it is found, the refinement from
    the start is not; with the stage off refine() is unchanged."""
    model, images, intrinsics, truth = _frames(48, slice(0, 40))
    train = TrainImages(images[::2], intrinsics[::2], truth[::2], torch.zeros(20, dtype=torch.long))
    query = slice(21, 22)  # between train frames 20 and 22
    starts = perturb(truth[query], torch.tensor([[1.0, -0.9, 0.6, 0.3, 0.2, -0.2]]))
    scenes = torch.zeros(1, dtype=torch.long)
    matching = MatchQueries(images[query], intrinsics[query], train)
    match = MatchSettings(width=48, render_width=0, start_views=2)
    queries = Queries(images[query], intrinsics[query], scenes)
    alone = refine(model, queries, starts, settings=SMALL_SEARCH)
    with_matching = queries._replace(matching=matching)
    found = refine(model, with_matching, starts, Calibration(match=match), settings=SMALL_SEARCH)
    assert float(pose_errors(alone.result.poses, truth[query])[0][0]) > 0.5
    assert float(pose_errors(found.result.poses, truth[query])[0][0]) < 0.1
    assert found.from_match.tolist() == [True] and found.matched.tolist() == [False]
    assert bool((found.result.score >= alone.result.score).all())
    off = refine(model, with_matching, starts, settings=SMALL_SEARCH)
    torch.testing.assert_close(off.poses, alone.poses)
    assert off.matched is None


def test_calibrate_keeps_the_stage_val_prefers_and_refine_applies_it(
    caplog: pytest.LogCaptureFixture,
) -> None:
    model, images, intrinsics, truth = _frames(48, slice(0, 40))
    train = TrainImages(images[::2], intrinsics[::2], truth[::2], torch.zeros(20, dtype=torch.long))
    rows = torch.tensor([5, 13, 21, 29])
    offset = torch.tensor([1.0, -0.9, 0.6, 0.3, 0.2, -0.2])
    starts = perturb(truth[rows], offset.expand(4, 6))
    scenes = torch.zeros(4, dtype=torch.long)
    matching = MatchQueries(images[rows], intrinsics[rows], train)
    queries = Queries(images[rows], intrinsics[rows], scenes, matching=matching)
    stages = [{}, {"width": 48, "render_width": 0, "start_views": 2}]
    options = CalibrationOptions(matches_from_val=stages)
    val = Validation(queries, starts, truth[rows])
    with caplog.at_level("INFO", logger="pae.render_compare.api"):
        calibration, refinement = calibrate(model, val, options, settings=SMALL_SEARCH)
    assert calibration.match.start_views == 2
    said = [r.getMessage() for r in caplog.records if "calibrate on val" in r.getMessage()]
    assert [line.split()[3] for line in said] == ["tried", "kept"]
    assert "'start_views': 2" in said[1]
    again = refine(model, queries, starts, calibration, settings=SMALL_SEARCH)
    torch.testing.assert_close(again.poses, refinement.poses)


@pytest.mark.parametrize(
    ("settings", "named"),
    [
        ({"detector": "akaze"}, "detector"),
        ({"width": 16}, "width"),
        ({"ratio": 1.5}, "ratio"),
        ({"start_views": -1}, "start_views"),
    ],
)
def test_match_settings_name_a_bad_value(settings: dict, named: str) -> None:
    with pytest.raises(ValueError, match=named):
        MatchSettings(**settings)


def test_matches_from_val_names_an_unknown_key() -> None:
    with pytest.raises(ValueError, match="radius is not a match setting"):
        CalibrationOptions(matches_from_val=[{"radius": 3}])


def test_views_without_train_images_are_a_one_line_error() -> None:
    model, images, intrinsics, truth = _frames(48, slice(0, 2))
    match = MatchSettings(width=48, render_width=0, start_views=2)
    with pytest.raises(ValueError, match=r"near_start_views need MatchQueries\.train"):
        queries = Queries(
            images, intrinsics, torch.zeros(2, dtype=torch.long),
            matching=MatchQueries(images, intrinsics),
        )  # fmt: skip
        refine(model, queries, truth, Calibration(match=match), settings=SMALL_SEARCH)


def test_the_train_cameras_nearest_the_start_are_starts_too() -> None:
    """near_start_views: the train cameras nearest the APR's start (not by appearance)."""
    from pae.render_compare.train_views import nearest_cameras

    model, images, intrinsics, truth = _frames(48, slice(0, 40))
    scenes = torch.zeros(40, dtype=torch.long)
    rows = nearest_cameras(truth[21:22], scenes[:1], truth[::2], scenes[::2], 2)
    assert sorted(rows[0].tolist()) == [10, 11]  # train frames 20 and 22 of the walk
    train = TrainImages(images[::2], intrinsics[::2], truth[::2], scenes[::2])
    start = perturb(truth[21:22], torch.tensor([[0.3, -0.3, 0.2, 0.1, 0.05, -0.05]]))
    match = MatchSettings(width=48, render_width=0, near_start_views=2)
    matching = MatchQueries(images[21:22], intrinsics[21:22], train)
    queries = Queries(images[21:22], intrinsics[21:22], scenes[:1], matching=matching)
    found = refine(model, queries, start, Calibration(match=match), settings=SMALL_SEARCH)
    assert float(pose_errors(found.result.poses, truth[21:22])[0][0]) < 0.1


def test_a_round_from_the_cameras_nearest_the_best_pose_never_lowers_a_score() -> None:
    model, images, intrinsics, truth = _frames(48, slice(0, 40))
    scenes = torch.zeros(40, dtype=torch.long)
    train = TrainImages(images[::2], intrinsics[::2], truth[::2], scenes[::2])
    rows = torch.tensor([5, 13, 21, 29])
    starts = perturb(truth[rows], torch.tensor([1.0, -0.9, 0.6, 0.3, 0.2, -0.2]).expand(4, 6))
    matching = MatchQueries(images[rows], intrinsics[rows], train)

    def refined(rounds: int) -> torch.Tensor:
        match = MatchSettings(width=48, render_width=0, near_start_views=1, near_best_rounds=rounds)
        queries = Queries(images[rows], intrinsics[rows], scenes[:4], matching=matching)
        return refine(
            model, queries, starts, Calibration(match=match), settings=SMALL_SEARCH
        ).result

    once, twice = refined(0), refined(1)
    assert bool((twice.score >= once.score).all())
    torch.testing.assert_close(twice.initial_score, once.initial_score)


def test_the_callback_names_a_second_width_and_an_unknown_descriptor() -> None:
    from pae.callbacks.render_compare import RenderCompareCallback

    with pytest.raises(ValueError, match=r"one width for every stage, not \[128, 256\]"):
        RenderCompareCallback(matches_from_val=[{"width": 256}, {"width": 128}])
    with pytest.raises(ValueError, match="match_descriptor: unknown 'gist'"):
        RenderCompareCallback(match_descriptor="gist")
    callback = RenderCompareCallback(matches_from_val=[{}, {"width": 64, "start_views": 2}])
    assert callback.match_inputs.width == 64
    assert not callback.options.uncalibrated().match.active  # two stages: val chooses


ANY_START_PLAIN = {"highpass_px": (), "contrast_px": (), "surface_shares": ()}
"""calibrate_any_start's own filter and surface share only: the tests' calibration short."""
NEAR_STAGE = {"width": 48, "render_width": 0, "near_start_views": 2, "below_score": 0.8}
"""A stage without keypoints: the 2 train cameras nearest each start below ZNCC 0.8."""


def _any_start_queries() -> tuple[OracleSceneModel, Queries, torch.Tensor]:
    """16 val queries of benchmark scene 0 (every third frame of 48 at 48 px), the train
    views the others in two, and their true poses [16, 7]."""
    model, images, intrinsics, truth = _frames(48, slice(0, 48))
    scenes = torch.zeros(48, dtype=torch.long)
    train = TrainImages(images[::2], intrinsics[::2], truth[::2], scenes[::2])
    rows = torch.arange(1, 48, 3)
    matching = MatchQueries(images[rows], intrinsics[rows], train)
    queries = Queries(images[rows], intrinsics[rows], scenes[rows], matching=matching)
    return model, queries, truth[rows]


def test_the_calibration_for_any_start_takes_a_stage_where_it_lowers_the_val_ratio() -> None:
    """calibrate_any_start with ``AnyStartOptions.matches``: the ladder's far starts (up to
    a third of the scene's size) lie beyond the search's basin, and the queries that score
    below 0.8 after it are refined from the train cameras nearest their starts too; the
    stage is chosen, its val log ratio lower than without it (-1.39 against -1.19 here),
    and refine() under the calibration with the same queries gives the same val poses."""
    from pae.render_compare import AnyStartOptions, calibrate_any_start
    from pae.render_compare.calibration import objective_value

    model, queries, truth = _any_start_queries()
    plain, stage = ANY_START_PLAIN, NEAR_STAGE

    def calibrated(**options: object) -> tuple[Calibration, float, torch.Tensor, torch.Tensor]:
        chosen, refinement, starts = calibrate_any_start(
            model, queries, truth, 4.0, SMALL_SEARCH, AnyStartOptions(**plain, **options)
        )
        value = objective_value(refinement.poses, starts, truth, "log_ratio")
        return chosen, value, refinement.poses, starts

    without, value_without, _, _ = calibrated()
    chosen, value, poses, starts = calibrated(matches=[stage])
    assert not without.match.active
    assert chosen.match == MatchSettings(**stage)
    assert value < value_without - 0.05
    again = refine(model, queries, starts, chosen, settings=SMALL_SEARCH)
    torch.testing.assert_close(again.poses, poses)


@pytest.mark.parametrize(("tolerance", "share"), [(10.0, 0.25), (-10.0, None)])
def test_the_stage_goes_to_the_fewest_queries_val_allows(
    monkeypatch: pytest.MonkeyPatch, tolerance: float, share: float | None
) -> None:
    """AnyStartOptions.stage_shares: with a tolerance nothing exceeds, the smallest share is
    kept (its threshold the quarter quantile of the val queries' scores from their starts)
    and refine() under it gives the other starts to exactly the queries scoring below it;
    with one nothing meets, the stage keeps its own threshold."""
    from pae.render_compare import AnyStartOptions, api, calibrate_any_start

    monkeypatch.setattr(api, "STAGE_SHARE_TOLERANCE", tolerance)
    model, queries, truth = _any_start_queries()
    plain, stage = ANY_START_PLAIN, NEAR_STAGE
    _, alone, _ = calibrate_any_start(
        model, queries, truth, 4.0, SMALL_SEARCH, AnyStartOptions(**plain)
    )
    options = AnyStartOptions(**plain, matches=[stage], stage_shares=(0.75, 0.25, 0.5))
    chosen, _, starts = calibrate_any_start(model, queries, truth, 4.0, SMALL_SEARCH, options)
    scores = alone.result.score.float()
    if share is None:
        assert chosen.match == MatchSettings(**stage)
        return
    below = float(torch.quantile(scores, share))
    assert chosen.match == MatchSettings(**stage | {"below_score": below})
    calls: list[int] = []
    original = RenderCompareRefiner.__call__

    def counted(self: RenderCompareRefiner, images: torch.Tensor, *args, **kwargs):
        calls.append(len(images))
        return original(self, images, *args, **kwargs)

    monkeypatch.setattr(RenderCompareRefiner, "__call__", counted)
    refine(model, queries, starts, chosen, settings=SMALL_SEARCH)
    needy = int((scores < below).sum())
    assert 0 < needy < len(truth)
    assert calls == [len(truth), 2 * needy]


def test_a_share_outside_zero_and_one_is_named() -> None:
    from pae.callbacks.render_compare import RenderCompareCallback

    with pytest.raises(ValueError, match=r"match_shares_from_val: 1.5 is not a share in \(0, 1\)"):
        RenderCompareCallback(match_shares_from_val=[0.5, 1.5])


def test_screening_refines_only_the_best_other_starts_and_still_finds_the_pose(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """screen_keep=1 of 4 other starts: the full search runs on the APR's start and one
    other start per query, the rest only the short search, and the query 1.5 m off is still
    found from the train view's pose; screen_keep at least the starts' count changes
    nothing."""
    model, images, intrinsics, truth = _frames(48, slice(0, 40))
    train = TrainImages(images[::2], intrinsics[::2], truth[::2], torch.zeros(20, dtype=torch.long))
    query = slice(21, 22)
    starts = perturb(truth[query], torch.tensor([[1.0, -0.9, 0.6, 0.3, 0.2, -0.2]]))
    matching = MatchQueries(images[query], intrinsics[query], train)
    scenes = torch.zeros(1, dtype=torch.long)
    queries = Queries(images[query], intrinsics[query], scenes, matching=matching)
    calls: list[tuple[int, int]] = []
    original = RenderCompareRefiner.__call__

    def counted(self: RenderCompareRefiner, images: torch.Tensor, *args, **kwargs):
        calls.append((self.rounds, len(images)))
        return original(self, images, *args, **kwargs)

    monkeypatch.setattr(RenderCompareRefiner, "__call__", counted)

    def refined(**screen: int) -> torch.Tensor:
        calls.clear()
        match = MatchSettings(width=48, render_width=0, start_views=2, near_start_views=2, **screen)
        found = refine(model, queries, starts, Calibration(match=match), settings=SMALL_SEARCH)
        return found.result.poses

    every = refined()
    assert calls == [(2, 1), (2, 4)]
    screened = refined(screen_keep=1)
    assert calls == [(2, 1), (1, 4), (2, 1)]
    assert float(pose_errors(screened, truth[query])[0][0]) < 0.1
    torch.testing.assert_close(refined(screen_keep=4), every)


def test_a_recorded_stage_reads_back_and_a_setting_it_predates_takes_its_default() -> None:
    from pae.render_compare.queries import match_figures, recorded_match

    stage = MatchSettings(width=64, start_views=4, detector="orb", screen_keep=2)
    figures = {f"test/m/{key}": value for key, value in match_figures(stage).items()}
    assert recorded_match(figures, "test/m") == stage
    older = {k: v for k, v in figures.items() if "screen" not in k}
    assert recorded_match(older, "test/m") == dataclasses.replace(stage, screen_keep=0)
    assert recorded_match({}, "test/m") is None


@pytest.mark.parametrize(
    ("settings", "said"),
    [
        ({}, "none"),
        (
            {"width": 64, "start_views": 4, "near_start_views": 4},
            "8 other starts + keypoints (128 px)",
        ),
        ({"width": 64, "render_width": 0, "start_views": 4}, "4 other starts"),
        ({"width": 64, "render_width": 0, "views": 4}, "keypoints (train views)"),
        (
            {"width": 64, "start_views": 4, "near_start_views": 4, "near_best_rounds": 1,
             "screen_keep": 2},
            "8 other starts + 1 round + keypoints (128 px), 2 in full",
        ),
        (
            {"width": 64, "start_views": 4, "below_score": 0.613},
            "4 other starts + keypoints (128 px), below ZNCC 0.61",
        ),
    ],
)  # fmt: skip
def test_a_stage_is_described_in_a_table_s_words(settings: dict, said: str) -> None:
    assert MatchSettings(**settings).described() == said


def test_correspondences_read_uint8_images_as_their_float_in_unit_range() -> None:
    """Queries held as uint8 (as pae-localize and the callback hold them) give the poses of
    the same images as float in [0, 1]."""
    model, images, intrinsics, truth = _frames(96, slice(0, 36, 12))
    starts = perturb(truth, torch.tensor([0.2, -0.15, 0.1, 0.1, -0.1, 0.05]).expand(3, 6))
    scenes = torch.zeros(3, dtype=torch.long)
    settings = MatchSettings(width=96, render_width=96, min_inliers=10, iterations=1)
    stored = (images * 255).round().to(torch.uint8)
    as_bytes = correspond(model, stored, intrinsics, starts, scenes, settings)
    as_floats = correspond(model, stored.float() / 255, intrinsics, starts, scenes, settings)
    assert as_bytes.found.any()
    for a, b in zip(as_bytes, as_floats, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
