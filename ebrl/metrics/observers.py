"""The metrics of the services that only watch the run: ``log`` (the tracking sinks) and ``viz`` (rerun)."""

from __future__ import annotations

from ebrl.metric import Metric

TRACKING = "tracking.py"
VIZ = "services/viz.py"

METRICS = (
    Metric("log/points", "points", "points written to the sinks ([Tracking](tracking.md))", TRACKING),
    Metric("log/episodes", "episodes", "episodes among them", TRACKING),
    Metric("log/env_steps", "steps", "the run's env steps as the tracker counts them", TRACKING),
    Metric("log/sinks", "sinks", "sinks open", TRACKING),
    Metric("log/nonfinite_dropped", "values", "NaN/inf values not written", TRACKING),
    Metric("log/sink_errors", "writes", "failed sink writes", TRACKING),
    Metric("log/dropped", "messages", "samples dropped when the log service fell behind", "services/log.py"),
    Metric("viz/spans", "spans", "spans logged to rerun ([Watching a run](watching.md))", VIZ),
    Metric("viz/reports", "reports", "stats reports logged to rerun", VIZ),
    Metric("viz/events", "events", "events logged to rerun", VIZ),
    Metric("viz/dropped", "messages", "messages dropped when the viewer bridge fell behind", VIZ),
)
