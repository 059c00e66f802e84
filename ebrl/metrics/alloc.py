"""The allocator's metrics (``alloc/*``, [The allocator](allocator.md)): its plan and the measured capacities it
re-plans from (``ebrl.alloc.runtime``, ``ebrl/services/alloc.py``)."""

from __future__ import annotations

from ebrl.metric import Metric

RUNTIME = "alloc/runtime.py"
SERVICE = "services/alloc.py"

METRICS = (
    Metric("alloc/plan_version", "version", "the plan in force (0: none yet)", RUNTIME),
    Metric("alloc/reallocations", "plans", "re-plans pushed", SERVICE, counter=True),
    Metric("alloc/reverts", "plans", "re-plans undone (the previous plan did better)", SERVICE, counter=True),
    Metric("alloc/observations", "observations", "observations of the stages' capacities taken (one per "
           "generation report, once every stage has reported)", SERVICE, counter=True),
    Metric("alloc/cores_<stage>", "cores", "the plan's cores for stage sim, gen or train", RUNTIME),
    Metric("alloc/cores_per_env", "cores", "cores each env worker is pinned to (Algorithm 1's c_env)", RUNTIME),
    Metric("alloc/theta_predicted", "decisions/s", "Algorithm 1's predicted throughput of the plan", RUNTIME),
    Metric("alloc/sim_capacity", "decisions/s", "the simulators' measured capacity (every host's)", RUNTIME),
    Metric("alloc/gen_capacity", "decisions/s", "generation's measured capacity", RUNTIME),
    Metric("alloc/train_capacity", "decisions/s", "training's measured capacity", RUNTIME),
    Metric("alloc/remote_sim_capacity", "decisions/s", "the other hosts' simulation capacity (part of "
           "`alloc/sim_capacity`)", RUNTIME),
    Metric("alloc/rollout_avg", "decisions/s", "moving average of the rollout capacity, min(sim, gen), over "
           "`alloc.window` observations", RUNTIME),
    Metric("alloc/train_avg", "decisions/s", "moving average of training's capacity", RUNTIME),
    Metric("alloc/gap", "fraction", "their relative gap, |rollout - train| / max", RUNTIME),
    Metric("alloc/imbalanced_reports", "observations", "observations in a row over `alloc.gap` (a re-plan at "
           "`alloc.patience`)", RUNTIME),
    Metric("alloc/sim_hosts", "hosts", "simulators reporting", SERVICE),
)
