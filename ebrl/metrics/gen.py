"""Generation's metrics (``gen/*``): the policy's forward passes, its weights, what waits for it."""

from __future__ import annotations

from ebrl.metric import Metric

SERVICE = "services/gen.py"
WEIGHTS = "weights.py"  # the weights taker
WAITING = "sched/batching.py"  # observations held back by the staleness bound
DEVICES = "devices.py"

METRICS = (
    Metric("gen/policy_version", "version", "weights version in use", SERVICE),
    Metric("gen/weights_applied", "versions", "weight versions loaded", SERVICE, counter=True),
    Metric("gen/weights_discarded", "versions", "incomplete large versions given up for a newer one", WEIGHTS),
    Metric("gen/weights_refused", "versions", "versions refused (not the policy's tensors, not finite, implausibly "
           "numbered)", WEIGHTS),
    Metric("gen/version_resets", "resets", "times generation found itself ahead of train (a forged version) and went "
           "back to train's weights", WEIGHTS),
    Metric("gen/batches", "passes", "forward passes", SERVICE, counter=True),
    Metric("gen/groups_served", "groups", "groups answered (a forward pass serves one or more)", SERVICE,
           counter=True),
    Metric("gen/envs_served", "envs", "envs answered", SERVICE, counter=True),
    Metric("gen/obs_queue", "messages", "observations received and not yet taken into a batch", SERVICE),
    Metric("gen/obs_waiting_for_policy", "messages", "observations held back by the staleness bound", WAITING),
    Metric("gen/throttled", "times", "times generation had only such held-back work", SERVICE, counter=True),
    Metric("gen/obs_waiting_dropped", "messages", "waiting observations dropped past the bound (64 x groups)",
           WAITING),
    Metric("gen/obs_dropped", "messages", "observations dropped for a shape that does not fit the policy or values "
           "that are not finite", WAITING),
    Metric("gen/sim_hosts", "hosts", "simulator hosts generation counts as serving (live ones of the run's plan): "
           "what its batch and the iteration schedule are sized by", SERVICE),
    Metric("gen/unknown_instances", "tokens", "liveliness tokens of a simulator instance the run does not have (its "
           "launcher's plan of hosts), each time one appeared: not counted as a host that serves (generation's "
           "batch, the iteration schedule), logged once. 0 under a client-mode launcher, whose router stops such "
           "tokens and counts them in `launcher/unknown_instances` ([security](security.md))", SERVICE),
    Metric("gen/cuda_device", "index", "the CUDA device generation runs on (-1: the CPU)", DEVICES),
    Metric("gen/cuda_mem_allocated_mb", "MiB", "on a GPU: memory in use by tensors", DEVICES),
    Metric("gen/cuda_mem_reserved_mb", "MiB", "on a GPU: memory held by torch's allocator", DEVICES),
    Metric("gen/cuda_mem_cap_mb", "MiB", "on a GPU: the memory cap (the allocator's share, else the device's memory)",
           DEVICES),
    Metric("gen/dtype", "bits", "the precision of the forward's matrix products (32: float32, 16: bfloat16 "
           "autocast): what `policy.dtype = \"auto\"` became ([GPUs](gpus.md))", "policies/graphs.py"),
    Metric("gen/compiled", "0/1", "whether the forward runs through CUDA graphs (1) or eagerly (0): what "
           "`gen.compile = \"auto\"` became", "policies/graphs.py"),
)
