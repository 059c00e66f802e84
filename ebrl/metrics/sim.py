"""The simulator's metrics (``sim/*``, and the host's ``cpu/*`` and ``gpu/*``, which the sim service reports)."""

from __future__ import annotations

from ebrl.metric import Metric

GROUP = "sched/group.py"  # the group loop: env steps, episodes, segments, the guard against bad numbers
FLEET = "sched/fleet.py"  # the episodes' and chunks' statistics
SERVICE = "services/sim.py"
CHOICE = "sched/stepchoice.py"  # core_rebinding = "auto"
STEPPING = "sched/stepping.py"  # core rebinding

METRICS = (
    Metric("sim/env_steps", "steps", "environment steps", GROUP, counter=True),
    Metric("sim/segments", "segments", "trajectory segments sent to training", GROUP, counter=True),
    Metric("sim/episodes", "episodes", "finished episodes", GROUP, counter=True),
    Metric("sim/episode_return_mean", "return", "mean return of the last 20 episodes, as the simulator counts "
           "them (what the run ends on is training's own, `train/episode_return_mean`)", FLEET),
    Metric("sim/success_rate", "fraction", "task success over the last 20 episodes (tasks with a success check: "
           "robosuite, ManiSkill, LIBERO)", FLEET),
    Metric("sim/chunk_latency_avg_ms", "ms", "time for a group to execute one action chunk: mean of the last 1000",
           FLEET),
    Metric("sim/chunk_latency_p50_ms", "ms", "the same, median", FLEET),
    Metric("sim/chunk_latency_p99_ms", "ms", "the same, 99th percentile", FLEET),
    Metric("sim/obs_resent", "messages", "observations re-published (after 30 s without an answer, or when a "
           "restarted gen appears)", GROUP, counter=True),
    Metric("sim/stale_actions_dropped", "messages", "answers for an old seq, dropped", GROUP, counter=True),
    Metric("sim/worker_restarts", "workers", "env workers replaced (died or hung past `sim.step_timeout`)", GROUP,
           counter=True),
    Metric("sim/partial_decisions_dropped", "decisions", "decisions of the replaced workers' unfinished episodes, "
           "dropped", GROUP, counter=True),
    Metric("sim/envs_given_up", "envs", "envs given up (their workers failed 6 times in a row)", SERVICE),
    Metric("sim/segments_while_train_down", "segments", "segments finished while no train was live (held)", GROUP,
           counter=True),
    Metric("sim/segments_sent_late", "segments", "held segments sent once a train was back", GROUP, counter=True),
    Metric("sim/segments_held", "segments", "segments held now", SERVICE),
    Metric("sim/segments_dropped_train_down", "segments", "held segments dropped over `train.max_pending` decisions",
           GROUP, counter=True),
    Metric("sim/rewards_clipped", "steps", "env step rewards clipped to `env.max_abs_reward`", GROUP, counter=True),
    Metric("sim/rewards_nonfinite", "steps", "rewards that were NaN or infinite, taken as 0", GROUP, counter=True),
    Metric("sim/obs_nonfinite", "steps", "observations that were not finite (their episode ended, a truncation)",
           GROUP, counter=True),
    Metric("sim/episode_records_dropped", "episodes", "episodes left out of an `EpisodeBatch` (more than 1024 ended "
           "in one stats interval)", FLEET),
    Metric("sim/step_busy_s", "CPU s", "CPU seconds inside env steps, a multi-threaded simulator's own threads "
           "included (per second: cores' worth of useful simulation)", GROUP, counter=True),
    Metric("sim/env_cores_used", "cores", "cores an env kept busy while it stepped, over the last interval (CPU time "
           "of its steps, every thread, over their wall time; above 1: a multi-threaded simulator, see "
           "`sim.cores_per_env`)", FLEET),
    Metric("sim/envs", "envs", "env workers", SERVICE),
    Metric("sim/cores", "cores", "cores the simulator holds (what an allocator on another host plans with)",
           SERVICE),
    Metric("sim/nice", "niceness", "the sim service's own niceness (`sim.nice`; 0 where it shares a process with "
           "other services)", SERVICE),
    Metric("sim/workers_nice", "niceness", "the lowest niceness of its env worker and vectorized group processes, "
           "as the kernel has it (`sim.nice`, in a shared process too); absent where none is a process", SERVICE),
    Metric("sim/unknown_instances", "tokens", "liveliness tokens of an instance the run does not have (its "
           "launcher's plan of hosts), each time one appeared: as `gen/unknown_instances`", SERVICE),
    # core rebinding (ebrl.sched.stepping) and its automatic choice (ebrl.sched.stepchoice)
    Metric("sim/core<c>_busy_s", "CPU s", "with core rebinding: seconds core c spent stepping envs (per second: its "
           "busy fraction)", SERVICE, counter=True),
    Metric("sim/rebinds", "re-pins", "with core rebinding: env worker re-pins to another core", STEPPING),
    Metric("sim/core_handoffs", "handoffs", "with core rebinding: cores handed from one env to another", STEPPING),
    Metric("sim/handoff_gap_us", "µs", "with core rebinding: mean time a handed core stood idle before its new env "
           "stepped on it", STEPPING),
    Metric("sim/core_rebinding", "0/1", "`sim.core_rebinding = \"auto\"`: 1 rebinding, 0 pinned whole chunks", CHOICE),
    Metric("sim/rebinding_gain", "ratio", "`\"auto\"`: rebinding's env steps/s over pinning's in the last trial "
           "(geometric mean over its pairs)", CHOICE),
    Metric("sim/stepping_trial", "0/1", "`\"auto\"`: 1 while a trial runs", CHOICE),
    Metric("sim/stepping_decisions", "decisions", "`\"auto\"`: decisions so far", CHOICE),
    Metric("sim/stepping_rate", "env steps/s", "`\"auto\"`: the env steps/s the chosen mode delivered in its last "
           "window", CHOICE),
    Metric("sim/step_latency_p50_ms", "ms", "`\"auto\"`: the recent steps' median latency, which a new trial "
           "watches", CHOICE),
    Metric("sim/step_latency_p90_ms", "ms", "`\"auto\"`: the recent steps' 90th-percentile latency", CHOICE),
    # the host
    Metric("cpu/core<i>_percent", "%", "utilisation of core i of the host (psutil), every core", SERVICE,
           services="sim"),
    Metric("gpu/<i>_sm_percent", "%", "SM utilisation of GPU i of the host (NVML; absent without a GPU)",
           "resources/nvml.py", services="sim"),
    Metric("gpu/<i>_mem_used_mb", "MiB", "memory in use on GPU i", "resources/nvml.py", services="sim"),
    Metric("gpu/<i>_mem_total_mb", "MiB", "memory of GPU i", "resources/nvml.py", services="sim"),
)
