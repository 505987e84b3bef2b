"""What the steps of pae-train and the evaluations of pae-eval share: the data and
checkpoints a step reads (`inputs`), the trainer that fits and tests it (`trainer`), the
record of its settings for TensorBoard's HParams tab (`hparams`) and the models of the
relative regressors (`relative`).

These modules read the step registry (`pae.steps`) but import no step's module
(`pae.steps.<name>`): the steps import them. Each step writes into its own directory:
checkpoints/, TensorBoard event files, and the figures it measured; the entry points merge
them into the run's metrics.json.
"""

Metrics = dict[str, float]
"""A step's figures by key (``test/teacher/pos_median_m``, ``bench/teacher/fit_s``, ...)."""
