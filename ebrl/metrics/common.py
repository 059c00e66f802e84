"""What every service reports about itself: its process (``proc/*``), its bus (``bus/*``), its cores and threads
(``quota/*``), control updates (``ctl/*``), busy time per lane (``busy/*``) and an injected slowdown."""

from __future__ import annotations

from ebrl import graph
from ebrl.metric import Metric

SERVICE = "service.py"
EVERY = graph.SERVICES  # ebrl.graph.ROLES' services
EVERY_AND_LAUNCHER = (*EVERY, "launcher")

METRICS = (
    Metric("busy/<lane>", "fraction", "fraction of the interval the lane spent in busy spans (the same spans the "
           "Gantt shows): `sim.g<group>`, `gen`, `train`, `weights`, `eval`, `replay`, ...", "meter.py",
           services=EVERY),
    Metric("quota/cores", "cores", "cores the service works on", SERVICE, services=EVERY),
    Metric("quota/threads", "threads", "torch threads (services that import torch)", SERVICE, services=EVERY),
    Metric("ctl/<kind>_applied", "updates", "control updates of kind `affinity` or `quota` applied", SERVICE,
           services=EVERY, counter=True),
    Metric("ctl/<kind>_ignored", "updates", "control updates ignored as already applied (an older version)", SERVICE,
           services=EVERY, counter=True),
    Metric("ctl/version_refused", "updates", "control updates refused as numbered more than 1000 "
           "(`ebrl.service.CONTROL_STEP`) past the last applied (the launcher: GPU shares)", (SERVICE, "launch.py"),
           services=EVERY_AND_LAUNCHER, counter=True),
    Metric("bus/malformed", "messages", "malformed (or wrong-version) messages dropped", SERVICE,
           services=EVERY_AND_LAUNCHER),
    Metric("bus/oversized", "messages", "of those, over their key's bound from the run's shapes (`ebrl/sizes.py`) or "
           "`bus.max_message_bytes` (one over the process's receive limit Zenoh drops uncounted)", SERVICE,
           services=EVERY_AND_LAUNCHER),
    Metric("bus/sender_dropped", "messages", "messages published without waiting (spans, events) and dropped by a "
           "full send queue", SERVICE,
           services=EVERY_AND_LAUNCHER),
    Metric("bus/local", "messages", "services sharing a process (`run.processes`): messages handed over by reference "
           "to services of the same process ([Services and processes](processes.md))", SERVICE, services=EVERY),
    Metric("bus/refused", "messages", "services sharing a process: messages its role may not send, refused before "
           "they left it", SERVICE, services=EVERY),
    Metric("proc/cpu_percent", "%", "the service process's CPU (percent of one core)", SERVICE, services=EVERY),
    Metric("proc/rss_mb", "MiB", "its resident memory", SERVICE, services=EVERY),
    Metric("proc/uptime_s", "s", "seconds since it started", SERVICE, services=EVERY),
    Metric("proc/loop_lag_max_ms", "ms", "the longest its event loop was held since the last report", SERVICE,
           services=EVERY),
    Metric("slowdown/injected_s", "s", "seconds added by `run.slowdown`", "meter.py", services=EVERY, counter=True),
)
