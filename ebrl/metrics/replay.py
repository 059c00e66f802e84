"""The replay service's metrics (``replay/*``): the transitions an off-policy algorithm's replay holds and draws."""

from __future__ import annotations

from ebrl.metric import Metric

SERVICE = "services/replay.py"

METRICS = (
    Metric("replay/size", "transitions", "transitions held", SERVICE),
    Metric("replay/capacity", "transitions", "the most it holds", SERVICE),
    Metric("replay/bytes", "bytes", "the bytes its arrays take", SERVICE),
    Metric("replay/inserted", "transitions", "transitions ever added (restored with its contents after a restart)",
           SERVICE),
    Metric("replay/sampled", "transitions", "transitions drawn for gradient steps", SERVICE),
    Metric("replay/insert_rate", "transitions/s", "transitions added per second since the previous report", SERVICE),
    Metric("replay/sample_rate", "transitions/s", "transitions drawn per second since the previous report", SERVICE),
    Metric("replay/lost", "transitions", "transitions training saw it hold that a restart could not read back "
           "(`replay.save`)", SERVICE),
    Metric("replay/requests", "requests", "requests for minibatches answered", SERVICE, counter=True),
    Metric("replay/saves", "writes", "writes of `RUN_DIR/replay.npz`", SERVICE, counter=True),
)
