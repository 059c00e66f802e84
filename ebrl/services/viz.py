"""viz service: the bus -> rerun bridge. Subscribes to ``ebrl/stats/<run>/**`` and logs the live Gantt and plots.

The only EBRL process that imports rerun-sdk. It never slows the run: its
inbox drops the oldest samples when it falls behind (counted as ``viz/dropped``).
"""

from __future__ import annotations

import asyncio
import os
import threading

from ebrl.messages import EpisodeBatch, Event, SpanBatch, decode_stats_sample
from ebrl.service import Service, service_main
from ebrl.viz.rerun_bridge import (RerunBridge, make_blueprint, open_recording, serve_web, stop_web,
                                  without_analytics)

FLUSH_S = 0.25
INBOX = 50_000


class VizService(Service):
    role = "viz"

    async def setup(self) -> None:
        viz = self.cfg.viz
        self.rrd_path = os.path.join(self.run_dir, "timeline.rrd")
        os.environ.update(without_analytics(self.run_dir))  # for the SDK here and the rerun processes it starts
        # web: the rerun CLI serves the page and the run on loopback; a child of this (main) thread
        self.web = serve_web(viz.port, viz.web_port, viz.memory_limit) if viz.rerun == "web" else None
        self.outlets, where = open_recording(viz.rerun, self.rrd_path, self.run_name, viz.port, viz.memory_limit,
                                             make_blueprint(viz.window_s), web_port=viz.web_port)
        self.bridge = RerunBridge(*self.outlets)
        self.lock = threading.Lock()  # the executor thread and teardown both log
        self.log.info("rerun: %s", where)
        self.event("viz", where)
        self.inbox = self.bus.subscribe(self.keys.sub("stats"), decode_stats_sample, policy="latest",
                                        capacity=INBOX)

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(FLUSH_S)
            # rerun calls off the event loop; every tick, so that each outlet sends at its pace
            await loop.run_in_executor(None, self.log_items, self.inbox.drain())

    def log_items(self, items, force: bool = False) -> None:
        with self.lock:
            for _, msg in items:
                if isinstance(msg, SpanBatch):
                    self.bridge.on_spans(msg)
                elif isinstance(msg, Event):
                    self.bridge.on_event(msg)
                elif isinstance(msg, EpisodeBatch):
                    continue  # the windowed means are in the sim's stats report
                else:
                    self.bridge.on_stats(msg)
            self.bridge.flush(force=force)

    def metrics(self) -> dict[str, float]:
        return {"viz/spans": float(self.bridge.spans), "viz/reports": float(self.bridge.reports),
                "viz/events": float(self.bridge.events), "viz/dropped": float(self.inbox.dropped)}

    async def teardown(self) -> None:
        self.log_items(self.inbox.drain(), force=True)
        for outlet in self.outlets:
            outlet.rec.flush(timeout_sec=5.0)
            outlet.rec.disconnect()  # closes its sink: the .rrd gets its footer
        if self.web is not None:
            stop_web(self.web)  # an open page keeps what it received


def main() -> None:
    service_main(VizService)


if __name__ == "__main__":
    main()
