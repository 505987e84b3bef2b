"""The steps of `pae-train`, in one registry: what each needs, trains and may change on resume.

`pae.train` runs them, `pae.config.validation` checks `stage.steps` and each step's checkpoints
against it, `pae.config.preflight` reads which settings a resumed run may change, and every
`conf/stage/*.yaml` lists names from it. Importing this module loads no torch: a sweep's
launching process reads it; a step's fit function, in the step's own module of this package
(``pae.steps.teacher``, ...), is imported when the step runs. Those modules import the
helpers they share from ``pae.runs``, and no step imports another.

To add a step: write its fit function in ``pae/steps/<name>.py`` (``fit(cfg, step_dir,
**checkpoints) -> (metrics, path of its last checkpoint)``, one keyword per entry of
``needs``), add a ``Step`` here, a config group ``conf/<group>/`` with ``max_epochs`` and
``optimizer``, and a ``conf/stage/`` file that lists it.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

CHECKPOINTS = ("teacher_ckpt", "student_ckpt", "decoder_ckpt", "scene_model_ckpt")
"""The run's checkpoint keys (conf/train.yaml): given on the command line or made by a step."""

Fit = Callable[..., tuple[dict[str, float], Path]]
"""``fit(cfg, step_dir, **checkpoints) -> (metrics, path of the step's last checkpoint)``."""


@dataclass(frozen=True)
class Step:
    """One step of a run.

    name: its name in ``stage.steps`` (and its folder in a run of several steps);
    group: the config group holding its training settings (``max_epochs``, ``optimizer``);
    fit: ``"module:function"`` of its fit function;
    needs: the checkpoint keys it reads (passed to ``fit`` by keyword), given or produced by
    an earlier step of the run; optional: checkpoint keys it reads when given (passed by
    keyword too, None when absent); produces: the checkpoint key its last checkpoint fills;
    resumable: the settings a resumed run may change for it (prefixes of dotted keys);
    models: the model configs it instantiates (dotted keys, each with a ``_target_``), each
    with the constructor arguments the fit function fills in itself (``n_scenes``): preflight
    checks their keys against the class's constructor. A model class may need checkpoints
    of its own (a class attribute ``needs``, e.g. a scene model's): they must be given or
    produced before the step like ``needs``, and reach ``fit`` through ``optional``.
    """

    name: str
    group: str
    fit: str
    needs: tuple[str, ...] = ()
    produces: str | None = None
    resumable: tuple[str, ...] = ()
    models: dict[str, tuple[str, ...]] = field(default_factory=dict)
    optional: tuple[str, ...] = ()

    def fit_function(self) -> Fit:
        """The fit function, imported now (it loads torch and Lightning)."""
        module, function = self.fit.split(":")
        return getattr(importlib.import_module(module), function)

    def run(self, cfg: Any, step_dir: Path, checkpoints: dict[str, Any]) -> tuple[dict, Path]:
        """Fit and test the step with the checkpoints it needs from ``checkpoints``."""
        keys = (*self.needs, *self.optional)
        return self.fit_function()(cfg, step_dir, **{key: checkpoints.get(key) for key in keys})


def _step(
    name: str,
    group: str,
    fit: str,
    models: dict[str, tuple[str, ...]],
    needs: tuple[str, ...] = (),
    produces: str | None = None,
) -> Step:
    return Step(name, group, fit, needs, produces, (f"{group}.max_epochs",), models)


STEPS: dict[str, Step] = {
    step.name: step
    for step in (
        # fits a scene model without a teacher: before the teacher when its novel views
        # need one (stage=novel_views), tested by the scene_model step after it
        _step(
            "scene_fit",
            "scene_model",
            "pae.steps.scene_fit:fit_scene",
            {"scene_model.model": ()},
            produces="scene_model_ckpt",
        ),
        # reads scene_model_ckpt with teacher.novel_views.enabled (pae.config.validation says so)
        Step(
            "teacher",
            "teacher",
            "pae.steps.teacher:fit_teacher",
            produces="teacher_ckpt",
            resumable=("teacher.max_epochs",),
            models={"teacher.model": ("n_scenes",)},
            optional=("scene_model_ckpt",),
        ),
        # reads scene_model_ckpt with student.novel_views or student.store_novel_views
        Step(
            "student",
            "student",
            "pae.steps.student:fit_student",
            ("teacher_ckpt",),
            "student_ckpt",
            ("student.max_epochs",),
            {"pae": ("n_scenes",)},
            ("scene_model_ckpt",),
        ),
        _step(
            "decoder",
            "decoder",
            "pae.steps.decoder:fit_decoder",
            {"decoder.model": ()},
            ("student_ckpt",),
            produces="decoder_ckpt",
        ),
        _step(
            "rpr",
            "rpr",
            "pae.steps.rpr:fit_rpr",
            {"rpr.model": ()},
            ("student_ckpt", "decoder_ckpt"),
        ),
        _step(
            "rpr_image",
            "rpr",
            "pae.steps.rpr_image:fit_rpr_image",
            {"rpr.model": ()},
            ("teacher_ckpt",),
        ),
        _step("iapr", "iapr", "pae.steps.iapr:fit_iapr", {"iapr.model": ()}, ("student_ckpt",)),
        # the model's class may read more checkpoints (its `needs`: scene_model=pae_decoder
        # reads the student and decoder), passed when given; given scene_model_ckpt, it
        # tests that model and fits none
        Step(
            "scene_model",
            "scene_model",
            "pae.steps.scene_model:fit_scene_model",
            ("teacher_ckpt",),
            "scene_model_ckpt",
            ("scene_model.max_epochs", "render_compare."),
            {"scene_model.model": ()},
            ("student_ckpt", "decoder_ckpt", "scene_model_ckpt"),
        ),
    )
}
"""Every step of pae-train by name, in the order a full run takes them."""

GROUPS: tuple[str, ...] = tuple(dict.fromkeys(step.group for step in STEPS.values()))
"""The config groups of the steps, each once (rpr_image trains with rpr's settings)."""

MODELS: dict[str, tuple[str, ...]] = {
    key: supplied for step in STEPS.values() for key, supplied in step.models.items()
}
"""Every model config a step builds -> the constructor arguments its step fills in."""
RESUMABLE_CHANGES: tuple[str, ...] = (
    "resume",
    "allow_other_data",
    "trainer.",
    "callbacks.",
    "logger.",
    "refine.",
    "data.num_workers",
    "data.eval_batch_size",
    *dict.fromkeys(key for step in STEPS.values() for key in step.resumable),
)
"""Settings a resumed run may change (``trainer.`` etc.: every key of the group): how the run
is executed and logged, test-time refinement, and each step's ``resumable`` (its epochs)."""


def steps_of(names: Any) -> list[Step]:
    """The registered steps named in ``names`` (``stage.steps``); an unknown name is a
    ValueError that lists the known ones."""
    unknown = [name for name in names if name not in STEPS]
    if unknown:
        raise ValueError(f"unknown stage.steps {unknown}; choose from {list(STEPS)}")
    return [STEPS[name] for name in names]


def missing_checkpoints(
    names: Any, given: dict[str, Any], model_needs: dict[str, tuple[str, ...]] | None = None
) -> list[tuple[str, str]]:
    """(step, checkpoint key) for every checkpoint a step of ``names`` needs (its ``needs``
    and ``model_needs[step name]``, what its models' classes need) that is neither in
    ``given`` (not None) nor produced by an earlier step of the run."""
    available = {key for key, value in given.items() if value is not None}
    missing = []
    for step in steps_of(names):
        needs = (*step.needs, *(model_needs or {}).get(step.name, ()))
        missing += [(step.name, key) for key in needs if key not in available]
        if step.produces:
            available.add(step.produces)
    return missing
