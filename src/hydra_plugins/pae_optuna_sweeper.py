"""pae's Hydra sweeper for an Optuna study (``conf/hydra/sweeper/pae_optuna.yaml``): the
adapter Hydra finds in its ``hydra_plugins`` namespace; the study itself is
:mod:`pae.config.optuna_study`. Hydra imports this module at every start, so it imports
neither optuna nor pae until a study runs."""

from __future__ import annotations

import logging

from hydra.core.plugins import Plugins
from hydra.errors import CompactHydraException
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)


class PaeOptunaSweeper(Sweeper):
    """Runs ``n_trials`` trials of the study ``study_name`` in ``storage`` (a database URL),
    ``n_jobs`` launched at a time, minimising (``direction``) what each job returns, sampled
    by ``sampler`` over ``params`` (Hydra's sweep syntax: choice, range, interval, tag(log,
    interval)). Trials of an earlier, stopped run of the study count towards ``n_trials``."""

    def __init__(
        self,
        storage: str,
        study_name: str,
        n_trials: int,
        n_jobs: int,
        direction: str,
        sampler: DictConfig | None,
        params: DictConfig | None = None,
    ) -> None:
        self.storage = storage
        self.study_name = study_name
        self.n_trials = n_trials
        self.n_jobs = n_jobs
        self.direction = direction
        self.sampler = sampler
        self.params = OmegaConf.to_container(params) if params else {}
        self.config: DictConfig | None = None

    def setup(
        self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig
    ) -> None:
        self.config = config
        self.hydra_context = hydra_context
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def sweep(self, arguments: list[str]) -> None:
        """Run the study; a setting it cannot use (its space, no optuna) is said in one line."""
        from pae.config.optuna_study import best_line, open_study, run_study, search_space
        from pae.core.errors import ConfigError

        try:
            space, fixed = search_space(self.params, arguments)
            study = open_study(self.storage, self.study_name, self.direction, self.sampler)
        except ConfigError as err:
            raise CompactHydraException(str(err)) from None
        log.info(f"study {self.study_name} in {self.storage}: {len(space)} searched settings")
        failure = run_study(study, space, fixed, self.n_trials, self.launcher.launch, self.n_jobs)
        log.info(best_line(study))
        if failure is not None:
            raise failure
