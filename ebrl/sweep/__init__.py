"""Hyperparameter sweeps on Optuna (``ebrl sweep``): a sweep file (:mod:`ebrl.sweep.spec`), each trial a real
``ebrl up`` followed over the bus and pruned from its learning curve (:mod:`ebrl.sweep.trial`,
:mod:`ebrl.sweep.curve`), trials shared by every process pointed at one storage (:mod:`ebrl.sweep.runner`),
and the results table, plots and best config (:mod:`ebrl.sweep.results`). docs/sweeps.md is the guide.

Only :mod:`ebrl.sweep.spec` and :mod:`ebrl.sweep.curve` work without Optuna (the ``sweep`` extra)."""
