"""The launcher's metrics (``launcher/*``): its report as ``launcher`` (``launcher/<host>`` on each host of a run
over several), on restarts, services up and what it refused."""

from __future__ import annotations

from ebrl.metric import Metric

LAUNCH = "launch.py"
SUPERVISOR = "supervisor.py"

METRICS = (
    Metric("launcher/restarts", "restarts", "services restarted after a failure", SUPERVISOR),
    Metric("launcher/restarts_<service>", "restarts", "the same, per service (summed over its instances)",
           SUPERVISOR),
    Metric("launcher/requotas", "starts", "services started again with a new GPU share (not restarts)", SUPERVISOR),
    Metric("launcher/services_live", "services", "services up (their liveliness tokens)", LAUNCH),
    Metric("launcher/ctl_unknown_service", "messages", "control messages for services the run lacks", LAUNCH),
    Metric("launcher/gpu_shares_refused", "messages", "GPU shares refused in a run that has none (no allocator on a "
           "GPU)", LAUNCH),
    Metric("launcher/stats_refused", "reports", "stats reports (or values) not taken: another instance's key, an "
           "instance the run lacks, not finite, an implausible training version", LAUNCH),
    Metric("launcher/returns_refused", "reports", "training returns not taken: moved further than the episodes "
           "finished since the last report could move them (`env.max_abs_reward`)", LAUNCH),
    Metric("launcher/unknown_instances", "tokens", "liveliness tokens of instances the run's plan does not name, each "
           "time one appeared (a client-mode launcher's router stops them: no other process sees them)", LAUNCH),
    Metric("launcher/hosts_refused", "links", "links Zenoh refused to a host that tried to join (a TLS handshake, a "
           "sign-in: [scaling out](scaling-out.md)), each try counted", LAUNCH),
)
