"""A Hydra sweep as an Optuna study (``hydra/sweeper=pae_optuna``, the ``hparams_search``
configs): each trial is one job of the sweep, run by the sweep's launcher, and the study lives
in a database (by default SQLite in the sweep directory), so that a stopped search continues
where it stopped. Optuna is imported only when a study runs (``pip install 'pae[optuna]'``)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import (
    ChoiceSweep,
    IntervalSweep,
    Override,
    RangeSweep,
    Transformer,
)
from hydra.core.utils import JobReturn
from omegaconf import DictConfig, OmegaConf

from pae.core.error_reporting import SweepJobFailed, first_line
from pae.core.errors import ConfigError

if TYPE_CHECKING:
    import optuna
    from optuna.distributions import BaseDistribution

log = logging.getLogger(__name__)

STUDY_SWEEPER = "hydra_plugins.pae_optuna_sweeper.PaeOptunaSweeper"
"""The ``_target_`` of ``conf/hydra/sweeper/pae_optuna.yaml``."""
SQLITE = "sqlite:///"
ERROR_ATTR = "error"
"""The user attribute of a trial whose job failed: its one-line error. A failed trial without
it was left running by a stopped sweep."""

Launch = Callable[[list[list[str]], int], Sequence[JobReturn]]
"""(each job's overrides, the first job's number) -> the jobs' returns: a Hydra launcher's
``launch``."""


def keeps_a_study(config: DictConfig) -> bool:
    """Whether the sweep of `config` is a study, whose sweep directory may already hold the
    trials of an earlier, stopped run of it."""
    return OmegaConf.select(config, "hydra.sweeper._target_", default=None) == STUDY_SWEEPER


def _distribution(override: Override) -> BaseDistribution:
    """The Optuna distribution of a sweep override: ``interval(a, b)`` a float (an int under
    ``int(...)``) uniform in [a, b], log-uniform under ``tag(log, ...)``; ``range(a, b, s)``
    the ints a, a + s, ... below b; ``choice(...)`` (or ``a,b,c``) its values as written."""
    from optuna.distributions import (
        CategoricalDistribution,
        FloatDistribution,
        IntDistribution,
    )

    value = override.value()
    if isinstance(value, IntervalSweep):
        use_log = "log" in value.tags
        if isinstance(value.start, int) and isinstance(value.end, int):
            return IntDistribution(value.start, value.end, log=use_log)
        return FloatDistribution(float(value.start), float(value.end), log=use_log)
    if isinstance(value, RangeSweep) and not value.shuffle:
        values = list(override.sweep_iterator())
        if len(values) > 1 and all(isinstance(v, int) for v in values):
            return IntDistribution(values[0], values[-1], step=values[1] - values[0])
    if isinstance(value, ChoiceSweep | RangeSweep):
        return CategoricalDistribution(
            list(override.sweep_iterator(transformer=Transformer.encode))
        )
    raise ConfigError(
        f"{override.input_line}: not a search space the study can sample (in "
        "hydra.sweeper.params or on the command line); use choice(...), range(a, b, step), "
        "interval(a, b) or tag(log, interval(a, b))"
    )


def search_space(
    params: Mapping[str, Any], arguments: Sequence[str]
) -> tuple[dict[str, BaseDistribution], list[str]]:
    """(each searched key -> its distribution, the overrides every trial gets) from the
    config's ``hydra.sweeper.params`` and the command line's `arguments`; a key given on the
    command line replaces the params' space of that key (a single value fixes it)."""
    parser = OverridesParser.create()
    searched = {
        override.get_key_element(): override
        for override in parser.parse_overrides([f"{k}={v}" for k, v in params.items()])
    }
    fixed = []
    for override in parser.parse_overrides(list(arguments)):
        if override.is_sweep_override() or override.get_key_element() in searched:
            searched[override.get_key_element()] = override
        else:
            fixed.append(override.input_line)
    space = {}
    for key, override in searched.items():
        if override.is_sweep_override():
            space[key] = _distribution(override)
        else:
            fixed.append(override.input_line)
    return space, fixed


def open_study(storage: str, name: str, direction: str, sampler: DictConfig | None) -> optuna.Study:
    """The study `name` in `storage` (a database URL), created if new, sampled by `sampler`
    (a Hydra config of an Optuna sampler; None: Optuna's default); a SQLite file's folder is
    made first."""
    try:
        import optuna
    except ImportError:
        raise ConfigError(
            "hydra/sweeper=pae_optuna (hparams_search=...) needs optuna: pip install 'pae[optuna]'"
        ) from None
    from hydra.utils import instantiate

    if storage.startswith(SQLITE):
        Path(storage.removeprefix(SQLITE)).parent.mkdir(parents=True, exist_ok=True)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna.create_study(
        storage=storage,
        study_name=name,
        direction=direction,
        sampler=None if sampler is None else instantiate(sampler),
        load_if_exists=True,
    )


def fail_stopped_trials(study: optuna.Study) -> list[int]:
    """Mark the trials a stopped run of the study left running as failed (without an
    ``error`` attribute: they are not counted); their numbers. Only one sweep uses the study:
    the sweep directory is locked (``pae.config.preflight``)."""
    from optuna.trial import TrialState

    stopped = [t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))]
    for number in stopped:
        study.tell(number, state=TrialState.FAIL)
    return stopped


def finished_trials(study: optuna.Study) -> int:
    """Trials that ran to their end: completed, or failed in their own job."""
    from optuna.trial import TrialState

    return sum(
        t.state == TrialState.COMPLETE
        or (t.state == TrialState.FAIL and ERROR_ATTR in t.user_attrs)
        for t in study.get_trials(deepcopy=False)
    )


def run_study(
    study: optuna.Study,
    space: Mapping[str, BaseDistribution],
    fixed: Sequence[str],
    n_trials: int,
    launch: Launch,
    batch: int = 1,
) -> BaseException | None:
    """Ask, launch and tell trials (`batch` at a time, each job numbered by its trial) until
    `n_trials` trials of the study have finished, counting those of earlier runs; a job's
    return value is the figure minimised. The first failed job's error, if any (the other
    trials still run)."""
    from optuna.trial import TrialState

    stopped = fail_stopped_trials(study)
    if stopped:
        log.warning(
            f"study {study.study_name}: trial(s) {stopped} were left running by a stopped "
            "sweep: marked failed, not counted"
        )
    if finished_trials(study):
        log.info(
            f"study {study.study_name}: {finished_trials(study)} of {n_trials} trials ran "
            "before; continuing"
        )
    failure = None
    while (left := n_trials - finished_trials(study)) > 0:
        trials = [study.ask(dict(space)) for _ in range(min(batch, left))]
        numbers = [trial.number for trial in trials]
        if numbers != list(range(numbers[0], numbers[0] + len(numbers))):
            raise ConfigError(
                f"study {study.study_name}: trials {numbers} are not consecutive: another "
                "process adds trials to this study"
            )
        jobs = [[*fixed, *(f"{k}={v}" for k, v in trial.params.items())] for trial in trials]
        for trial, result in zip(trials, launch(jobs, numbers[0]), strict=True):
            try:
                value = result.return_value
                if value is None:
                    raise SweepJobFailed(
                        f"a sweep job failed (trial {trial.number}): the run gave no "
                        "validation figure to minimise"
                    )
            except Exception as err:
                trial.set_user_attr(ERROR_ATTR, first_line(err))
                study.tell(trial, state=TrialState.FAIL)
                failure = failure or err
                continue
            study.tell(trial, float(value))
    return failure


def best_line(study: optuna.Study) -> str:
    """One line: the study's best trial, its value and settings; or that none completed."""
    from optuna.trial import TrialState

    if not study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        return f"study {study.study_name}: no trial completed"
    best = study.best_trial
    settings = " ".join(f"{k}={v}" for k, v in best.params.items())
    return (
        f"study {study.study_name}: best trial {best.number}, value {best.value:.4g} ({settings})"
    )
