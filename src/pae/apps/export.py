"""A finished run's networks as ONNX files (`pae-export`): the teacher (image -> pose, latent
and, for a multi-scene teacher, scene logits) and its student's PAE (pose -> latent), with the
pre-processing written beside them (``MANIFEST``), for onnxruntime or any other ONNX runtime.

Exported with ``torch.onnx.export(dynamo=True)`` (torch.export, then onnxscript), the batch
axis dynamic; every graph is run by onnxruntime at another batch size than the one it was
exported at and compared with the model before anything is written."""

from __future__ import annotations

import contextlib
import io
import re
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from pae.apps import localization as loc
from pae.core.atomic import atomic_write, check_writable_dir, write_json_atomic
from pae.core.checkpoints import load_pae, load_teacher
from pae.core.errors import ExportError
from pae.core.geometry import normalize_pose
from pae.data.transforms import IMAGENET_MEAN, IMAGENET_STD

MANIFEST = "pae_export.json"
"""The file beside the ONNX files: their names, inputs, outputs and the pre-processing."""
TEACHER_FILE = "teacher.onnx"
PAE_FILE = "pae.onnx"
EXPORT_BATCH = 2
"""The batch the graphs are exported at (torch.export fixes a batch of 1 as a constant)."""
CHECK_BATCH = 3
"""The batch each exported graph is checked at against the model."""
CHECK_TOLERANCE = 1e-3
"""Largest |difference| between onnxruntime's outputs and the model's (relative to the
output's largest |value|, at least 1) that the check accepts: float32 rounding, not a bug."""
POSE_CONVENTION = (
    "x, y, z (m), qw, qx, qy, qz: camera-to-world (X_world = R(q) X_camera + t, t the camera "
    "centre), camera axes x right, y down, z forward; unit quaternion"
)


class TeacherGraph(nn.Module):
    """What the exported teacher computes: image [B, 3, crop, crop] (normalised) -> pose
    [B, 7] (``POSE_CONVENTION``), latent [B, 2d] ([z_x, z_q], what a PAE's latent is matched
    with) and, for a multi-scene teacher, scene_logits [B, S]."""

    def __init__(self, teacher: nn.Module) -> None:
        super().__init__()
        self.teacher = teacher

    def forward(self, image: Tensor) -> tuple[Tensor, ...]:
        raw_pose, latents = self.teacher(image)
        outputs = (normalize_pose(raw_pose), latents.joint())
        return outputs if latents.scene_logits is None else (*outputs, latents.scene_logits)


class PaeGraph(nn.Module):
    """What the exported PAE computes: pose [B, 7] (``POSE_CONVENTION``) and, for a
    multi-scene PAE, scene [B] (int64, an index into the scene list) -> latent [B, 2d]."""

    def __init__(self, pae: nn.Module) -> None:
        super().__init__()
        self.pae = pae

    def forward(self, pose: Tensor, scene: Tensor | None = None) -> Tensor:
        return self.pae(pose, scene).joint()


def _causes(err: BaseException) -> Iterator[BaseException]:
    """``err`` and the errors it was raised from or while handling, outermost first."""
    seen: set[int] = set()
    cause: BaseException | None = err
    while cause is not None and id(cause) not in seen:
        seen.add(id(cause))
        yield cause
        cause = cause.__cause__ or cause.__context__


def _reason(err: BaseException) -> str:
    """The first line of the innermost error behind an exporter's error (its own message
    is a page of advice)."""
    message = str(list(_causes(err))[-1]).strip()
    line = (message.splitlines() or [type(err).__name__])[0]
    return line[:240]


def _shown(model: nn.Module, module: nn.Module) -> str:
    """``module`` as the error names it: its name in ``model`` and its class."""
    name = next(name for name, found in model.named_modules() if found is module)
    return f"{name} ({type(module).__name__})" if name else type(module).__name__


def _module_in_traceback(model: nn.Module, err: BaseException) -> str | None:
    """The innermost submodule of ``model`` whose code the error was raised in (``model``'s
    own class name for itself), or None when none was running."""
    names = {id(module): name for name, module in model.named_modules()}
    for cause in _causes(err):
        found = None
        trace = cause.__traceback__
        while trace is not None:
            owner = trace.tb_frame.f_locals.get("self")
            if id(owner) in names:
                found = owner
            trace = trace.tb_next
        if found is not None:
            return _shown(model, found)
    return None


def _module_calling(model: nn.Module, operator: str, example: tuple[Tensor, ...]) -> str | None:
    """The first submodule of ``model`` whose own code calls the aten ``operator`` (e.g.
    ``_linalg_eigh``) in an eager run on ``example``, or None when none does."""
    from torch.utils._python_dispatch import TorchDispatchMode

    running: list[str] = []
    found: list[str] = []

    class Calls(TorchDispatchMode):
        def __torch_dispatch__(
            self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None
        ) -> Any:
            if func.overloadpacket.__name__ == operator and running and not found:
                found.append(running[-1])
            return func(*args, **(kwargs or {}))

    def entered(module: nn.Module, args: Any) -> None:
        running.append(_shown(model, module))

    def left(module: nn.Module, args: Any, output: Any) -> None:
        running.pop()

    hooks = []
    for module in model.modules():
        hooks += [module.register_forward_pre_hook(entered), module.register_forward_hook(left)]
    try:
        with torch.no_grad(), Calls():
            model(*example)
    except Exception:  # the model's own failure: its traceback names the module instead
        pass
    finally:
        for hook in hooks:
            hook.remove()
    return found[0] if found else None


def failing_layer(model: nn.Module, err: BaseException, example: tuple[Tensor, ...]) -> str:
    """The layer of ``model`` an exporter's error comes from: the module it was raised in
    while tracing, else the first module that calls the operator it names; "the model"
    where neither is found."""
    layer = _module_in_traceback(model, err)
    operator = re.search(r"aten[.:]+(\w+)", _reason(err))
    if layer is None and operator is not None:
        layer = _module_calling(model, operator.group(1), example)
    return "the model" if layer is None else f"layer {layer}"


def onnx_bytes(
    graph: nn.Module,
    example: tuple[Tensor, ...],
    inputs: list[str],
    outputs: list[str],
    what: str,
) -> bytes:
    """The ONNX model (serialised) of ``graph`` (eval mode) on inputs like ``example``
    (tensors whose first axis is the batch, dynamic in the graph), checked with onnxruntime
    at a batch of ``CHECK_BATCH``; an ExportError in one line naming ``what`` and the layer
    the exporter failed at, or the output that differs."""
    graph = graph.eval()
    batch = torch.export.Dim("batch", min=1)
    try:  # torch.export writes the graph of a model it refuses to stderr: the error says it
        with warnings.catch_warnings(), contextlib.redirect_stderr(io.StringIO()):
            warnings.filterwarnings("ignore", message=".*axis name.*")  # inputs share the batch
            program = torch.onnx.export(
                graph,
                example,
                dynamo=True,
                verbose=False,
                input_names=inputs,
                output_names=outputs,
                dynamic_shapes=tuple({0: batch} for _ in example),
            )
    except Exception as err:
        layer = failing_layer(graph, err, example)
        raise ExportError(f"{what}: {layer} cannot be exported to ONNX: {_reason(err)}") from None
    assert program is not None
    model = program.model_proto.SerializeToString()
    check_graph(graph, model, example, outputs, what)
    return model


def _resized(example: Tensor, batch: int, generator: torch.Generator) -> Tensor:
    """An input like ``example`` with ``batch`` rows: random values of its dtype (integers:
    from 0 to ``example``'s largest)."""
    shape = (batch, *example.shape[1:])
    if example.is_floating_point():
        return torch.randn(shape, generator=generator, dtype=example.dtype)
    high = int(example.max()) + 1
    return torch.randint(0, high, shape, generator=generator, dtype=example.dtype)


def check_graph(
    graph: nn.Module, model: bytes, example: tuple[Tensor, ...], outputs: list[str], what: str
) -> None:
    """ExportError unless onnxruntime's outputs of ``model`` at a batch of ``CHECK_BATCH``
    match ``graph``'s (``CHECK_TOLERANCE``): an export that fixed the batch it was traced at,
    or computed something else, is never written."""
    import onnxruntime

    session = onnxruntime.InferenceSession(model, providers=["CPUExecutionProvider"])
    generator = torch.Generator().manual_seed(0)
    given = [_resized(tensor, CHECK_BATCH, generator) for tensor in example]
    names = [entry.name for entry in session.get_inputs()]
    try:
        found = session.run(outputs, {n: t.numpy() for n, t in zip(names, given, strict=True)})
    except Exception as err:
        first = (str(err).strip().splitlines() or [type(err).__name__])[0][:240]
        raise ExportError(
            f"{what}: the exported graph fails at a batch of {CHECK_BATCH} (exported at "
            f"{EXPORT_BATCH}: the model fixes its batch size): {first}"
        ) from None
    with torch.no_grad():
        expected = graph(*given)
    expected = expected if isinstance(expected, tuple) else (expected,)
    for name, ours, theirs in zip(outputs, expected, found, strict=True):
        scale = max(1.0, float(ours.abs().max()))
        differs = float(np.abs(theirs - ours.numpy()).max()) / scale
        if not differs <= CHECK_TOLERANCE:
            raise ExportError(
                f"{what}: the exported graph's {name} differs from the model's by "
                f"{differs:.3g} (relative) at a batch of {CHECK_BATCH}: the model fixes "
                "something at export (its batch size, a value read from a tensor)"
            )


def _describe(shape: str, meaning: str, dtype: str = "float32") -> dict[str, str]:
    """A manifest's entry of one input or output."""
    return {"dtype": dtype, "shape": shape, "meaning": meaning}


def export_run(run_dir: str | Path, out: str | Path) -> dict[str, Any]:
    """Write ``run_dir``'s teacher (``TEACHER_FILE``) and, where the run trained one, its
    student's PAE (``PAE_FILE``) to ``out`` as ONNX, then ``MANIFEST`` (each file whole,
    the manifest last); returns the manifest."""
    out = Path(out)
    check_writable_dir(out, "OUT")
    run = loc.read_run(run_dir)
    step = "teacher" if "teacher" in run.steps else run.steps[0]
    teacher_path = run.checkpoint(step, "pae-export")
    teacher = load_teacher(teacher_path)
    data = loc.data_module(run)
    crop = int(data.crop)
    scenes = list(teacher.scene_names)
    multi = len(scenes) > 1
    d = 2 * int(teacher.model.latent_dim)
    example = (torch.zeros(EXPORT_BATCH, 3, crop, crop),)
    outputs = ["pose", "latent", *(["scene_logits"] if multi else [])]
    model = onnx_bytes(TeacherGraph(teacher.model), example, ["image"], outputs, "teacher")
    with atomic_write(out / TEACHER_FILE, "wb") as handle:
        handle.write(model)
    teacher_outputs = {
        "pose": _describe("[B, 7]", "the camera's pose (pose_convention)"),
        "latent": _describe(f"[B, {d}]", "[z_x, z_q], what kNN refinement matches"),
    }
    if multi:
        teacher_outputs["scene_logits"] = _describe(
            f"[B, {len(scenes)}]", "one per scene of `scenes`: the argmax is the image's scene"
        )
    manifest: dict[str, Any] = {
        "teacher": {
            "file": TEACHER_FILE,
            "checkpoint": str(teacher_path),
            "inputs": {"image": _describe(f"[B, 3, {crop}, {crop}]", "pre-processed image")},
            "outputs": teacher_outputs,
        },
        "preprocessing": {
            "read": "RGB, 8 bits per channel",
            "resize_shorter_edge_px": int(data.shorter_edge),
            "resize_interpolation": "area when shrinking, bilinear when enlarging (OpenCV)",
            "center_crop_px": crop,
            "input_size": [crop, crop],
            "scale": 1 / 255,
            "mean": list(IMAGENET_MEAN),
            "std": list(IMAGENET_STD),
            "layout": "NCHW, (RGB / 255 - mean) / std",
        },
        "scenes": scenes,
        "fingerprint": teacher.data_fingerprint,
        "pose_convention": POSE_CONVENTION,
        "run": str(run.folder),
        "exporter": f"torch.onnx.export(dynamo=True), torch {torch.__version__}",
    }
    if "student" in run.steps:
        student_path = run.checkpoint("student", "pae-export")
        pae = load_pae(student_path)
        example = (torch.zeros(EXPORT_BATCH, 7), torch.arange(EXPORT_BATCH) % len(scenes))
        example = example if multi else example[:1]
        inputs = ["pose", "scene"][: len(example)]
        model = onnx_bytes(PaeGraph(pae.model), example, inputs, ["latent"], "student's PAE")
        with atomic_write(out / PAE_FILE, "wb") as handle:
            handle.write(model)
        pae_inputs = {"pose": _describe("[B, 7]", "a camera's pose (pose_convention)")}
        if multi:
            pae_inputs["scene"] = _describe("[B]", "index into `scenes`", "int64")
        manifest["pae"] = {
            "file": PAE_FILE,
            "checkpoint": str(student_path),
            "inputs": pae_inputs,
            "outputs": {"latent": _describe(f"[B, {d}]", "[z_x, z_q], as the teacher's")},
        }
    write_json_atomic(out / MANIFEST, manifest)
    return manifest
