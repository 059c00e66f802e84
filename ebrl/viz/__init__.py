"""Observability: the run recording (stats, spans, events), the rerun bridge, the static report.

Only :mod:`ebrl.viz.rerun_bridge` imports rerun-sdk, and only the viz service
imports it; every other process publishes spans and stats on the bus.
"""
