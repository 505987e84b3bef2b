import numpy as np
import pytest
import torch

from pae.callbacks.trajectory import GROUND_TRUTH_RGB, METHOD_RGB, trajectory_figure


def _columns_with(image: np.ndarray, colour: tuple[int, int, int]) -> np.ndarray:
    return np.flatnonzero((image == colour).all(-1).any(0))


def test_trajectory_figure_draws_each_method_in_its_colour_on_one_metre_scale() -> None:
    gt = torch.zeros(3, 7)
    gt[:, 3] = 1
    gt[:, 0] = torch.tensor([0.0, 1.0, 2.0])  # along x: x is the horizontal axis
    gt[:, 1] = torch.tensor([0.0, 0.1, 0.0])
    teacher = gt + torch.tensor([0.0, 0.5, 0, 0, 0, 0, 0])
    refined = gt.clone()
    refined[:, 0] += 0.2
    image = trajectory_figure("scene00: test", gt, {"teacher": teacher, "refined": refined})
    assert image.shape == (540, 720, 3) and image.dtype == np.uint8
    colours = {tuple(c) for c in image.reshape(-1, 3)}
    assert {GROUND_TRUTH_RGB, METHOD_RGB[0], METHOD_RGB[1], (0, 0, 0)} <= colours
    # ground truth spans 2 m, refined the same 2 m shifted right by 0.2 m, on one scale
    plot = image[:, :-230]  # without the legend
    gt_cols, refined_cols = (
        _columns_with(plot, GROUND_TRUTH_RGB),
        _columns_with(plot, METHOD_RGB[1]),
    )
    metre_px = (gt_cols.max() - gt_cols.min()) / 2.0
    shift_px = refined_cols.min() - gt_cols.min()
    assert shift_px == pytest.approx(0.2 * metre_px, abs=2)
    # the legend holds a swatch of each colour, in order: ground truth, teacher, refined
    legend = image[:, -230:]
    rows = [
        np.flatnonzero((legend == c).all(-1).any(1)).min()
        for c in (GROUND_TRUTH_RGB, *METHOD_RGB[:2])
    ]
    assert rows == sorted(rows)


class _Recorder:
    """The parts of a StudentModule and Trainer the refinement callback reads."""

    def __init__(self, pae: torch.nn.Module, outputs: dict[str, torch.Tensor]) -> None:
        self.pae = pae
        self.scene_names = ["room"]
        self.eval_outputs = [outputs]
        self.logged: dict[str, float] = {}

    def log_dict(self, figures: dict[str, torch.Tensor]) -> None:
        self.logged |= {key: float(value) for key, value in figures.items()}


class _Data:
    def __init__(self, poses: torch.Tensor) -> None:
        self.poses = poses

    def store_poses(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.poses, torch.zeros(len(self.poses), dtype=torch.long)


class _Trainer:
    def __init__(self, poses: torch.Tensor) -> None:
        self.datamodule = _Data(poses)
        self.world_size = 1
        self.loggers: list = []


def _poses(n: int, offset: float, generator: torch.Generator) -> torch.Tensor:
    positions = torch.rand(n, 3, generator=generator) * 4 + offset
    quaternions = torch.nn.functional.normalize(torch.randn(n, 4, generator=generator), dim=1)
    return torch.cat([positions, quaternions * quaternions[:, :1].sign()], dim=1)


def _run(audit: bool, repeats: int = 0) -> dict[str, float]:
    """Queries whose estimate is their true pose; train poses shifted 0.3 m away from them.
    The first ``repeats`` queries come again at the end, as a distributed sampler pads."""
    from pae.callbacks.refinement import TestTimeRefinement
    from pae.models.pae import PoseAutoEncoder
    from pae.refine import LatentRetrievalRefiner

    generator = torch.Generator().manual_seed(0)
    test = _poses(40, 0.0, generator)
    train = test.clone()
    train[:, 0] += 0.3
    torch.manual_seed(0)  # the same PAE in every call, whatever ran before
    pae = PoseAutoEncoder(latent_dim=16, L=2)
    with torch.no_grad():
        latents = pae(test)
    outputs = {
        "z": latents.joint(),
        "estimate": test,
        "pose": test,
        "scene": torch.zeros(40, dtype=torch.long),
        "scene_estimate": torch.zeros(40, dtype=torch.long),
        "index": torch.arange(40),
    }
    outputs = {key: torch.cat([value, value[:repeats]]) for key, value in outputs.items()}
    callback = TestTimeRefinement(
        k=1,
        guess_sigma_m=0.5,
        trajectory_plot=False,
        audit=audit,
        alternatives={"latent_knn": lambda index, pae: LatentRetrievalRefiner(index, pae, k=1)},
    )
    trainer, module = _Trainer(train), _Recorder(pae, outputs)
    callback.setup(trainer, module, "test")
    callback.refine(trainer, module, "test")
    return module.logged


def test_test_store_retrieves_the_query_own_pose_and_the_train_store_never_does() -> None:
    logged = _run(audit=True)
    # k=1 in the evaluated split's own poses: the nearest is the query's own pose
    assert logged["test/knn_mean_test_store/pos_median_m"] < 1e-5
    assert logged["test/refined_test_store/pos_median_m"] < 1e-5
    assert (
        logged["test/guess_refined_test_store/pos_median_m"]
        < logged["test/guess_initial/pos_median_m"]
    )
    # the train store holds no test pose: every train row is 0.3 m from its query
    for method in ("knn_mean", "refined", "latent_knn"):
        assert abs(logged[f"test/{method}/pos_median_m"] - 0.3) < 1e-4, method
    assert abs(logged["test/diagnostics/gt_to_train_m"] - 0.3) < 1e-4
    assert logged["test/diagnostics/estimate_to_train_per_error"] > 1e3


def test_audit_false_skips_the_test_store_rows() -> None:
    logged = _run(audit=False)
    assert "test/refined/pos_median_m" in logged and "test/knn_mean/pos_median_m" in logged
    assert not [key for key in logged if "_test_store" in key]


def test_padding_repeats_are_counted_once() -> None:
    once, padded = _run(audit=True), _run(audit=True, repeats=3)
    assert padded.keys() == once.keys()
    for key, value in once.items():
        if not key.startswith("bench/"):
            assert padded[key] == value, key


def test_pose_error_metric_counts_each_index_once() -> None:
    from pae.core.metrics import PoseErrorMetric

    generator = torch.Generator().manual_seed(1)
    target = _poses(9, 0.0, generator)
    pred = target + 0.1 * torch.randn(9, 7, generator=generator)
    plain, padded = PoseErrorMetric(), PoseErrorMetric()
    plain.update(pred, target, index=torch.arange(9))
    padded.update(pred[:5], target[:5], index=torch.arange(5))
    padded.update(pred[4:], target[4:], index=torch.arange(4, 9))
    padded.update(pred[:2], target[:2], index=torch.arange(2))
    for key, value in plain.compute().items():
        assert padded.compute()[key] == value, key
