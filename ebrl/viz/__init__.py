"""Observability: the run recording (stats, spans, events), the rerun bridge, the static report.

Only :mod:`ebrl.viz.rerun_bridge` imports rerun-sdk, and only the viz service
imports it; every other process publishes spans and stats on the bus.
"""


def web_url(port: int, web_port: int) -> str:
    """The page of rerun's web viewer (``viz.rerun = "web"``), told to connect to the run's gRPC server on
    ``port``; both listen on 127.0.0.1."""
    from urllib.parse import quote

    return f"http://127.0.0.1:{web_port}/?url=" + quote(f"rerun+http://127.0.0.1:{port}/proxy", safe="")
