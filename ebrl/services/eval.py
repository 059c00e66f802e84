"""eval service: evaluates new policy versions on held-out seeds; reports, videos and the best policy.

It receives the weights as generation does (``ebrl.weights``), evaluates every ``eval.every``-th version (and the
final one) in its own env worker processes at idle priority on ``eval.cores``, and publishes each result as a
stats report of ``eval/0`` (``eval/return``, ``eval/success_rate`` with their 95 % intervals, ...). Versions it
cannot keep up with are dropped, the newest kept (``ebrl.evaluate.EvalSchedule``). Nothing waits for it: the
launcher runs it as an optional service, so its death never stops the run.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import dataclasses
import os
import time

from ebrl import sizes, threads
from ebrl.evaluate import BestPolicy, EvalPool, EvalResult, EvalSchedule, lower_priority
from ebrl.policies import load_arrays, make_policy
from ebrl.policies.checkpoint import policy_metadata, portable_metadata
from ebrl.service import Service, env_info, service_main
from ebrl.weights import WeightsLayout, WeightsReceiver, known_version


class EvalService(Service):
    role = "eval"

    async def setup(self) -> None:
        cfg = self.cfg
        priority = lower_priority()  # before the workers start: they inherit it
        threads.set_threads(1)
        info = await env_info(self)
        bounds = self.bounds or await self.message_bounds()
        self.model = make_policy(dataclasses.replace(cfg.policy, checkpoint=""), info.layout, info.action_dim,
                                 info.bounds)
        self.metadata = {**policy_metadata(self.model), **portable_metadata(cfg.policy, cfg.env, info),
                         "run": self.run_name}
        self.workers = EvalPool(self.metadata, cfg.eval.cores, render=cfg.eval.video_episodes > 0)
        self.thread = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="eval")  # waits on the workers
        self.schedule = EvalSchedule(cfg.eval.every, cfg.run.iterations)
        self.best = BestPolicy(os.path.join(self.run_dir, "best.safetensors"))
        self.newest = -1
        self.evaluations = 0
        self.video_dir: str | None = None  # of the evaluation in progress
        self.busy = False
        self.wake, self.due = asyncio.Event(), asyncio.Event()
        self.weights = WeightsReceiver(self.bus, self.run_name, notify=self.wake, role=self.role,
                                       layout=WeightsLayout.of_model(self.model), floor=known_version(self.run_dir),
                                       follow=True,  # back to train's weights if a forged version put eval ahead
                                       max_bytes=bounds.weights)
        self.log.info("evaluating every %d versions, %d episodes from seed %d, %d worker(s) at %s", cfg.eval.every,
                      cfg.eval.episodes, cfg.eval.seeds, self.workers.workers, priority)

    async def message_bounds(self) -> sizes.Bounds:
        """Weights: the run's bound (ebrl.sizes), from the policy's tensors."""
        info = await env_info(self)
        return await asyncio.get_running_loop().run_in_executor(None, lambda: sizes.of_run(self.cfg, info,
                                                                                           weights=True))

    async def run(self) -> None:
        collector = asyncio.create_task(self.collect())
        try:
            await self.weights.request(timeout=10.0)  # a (re)started eval: the newest version now
            self.wake.set()
            while True:
                await self.due.wait()
                self.due.clear()
                weights = self.schedule.take()
                if weights is not None:
                    await self.evaluate(weights)
        finally:
            collector.cancel()

    async def collect(self) -> None:
        """Take every version as it completes; the due ones wait for the evaluation loop (keep-latest)."""
        while True:
            await self.wake.wait()
            self.wake.clear()
            weights = self.weights.take_newer(self.newest)
            if weights is None:
                continue
            self.newest = weights.version
            if self.schedule.offer(weights):
                self.due.set()

    async def evaluate(self, weights) -> None:
        e, loop, version = self.cfg.eval, asyncio.get_running_loop(), weights.version
        video_dir = os.path.join(self.run_dir, "videos", f"v{version}") if e.video_episodes else None
        start, self.busy, self.video_dir = time.time(), True, video_dir
        try:
            result = await loop.run_in_executor(self.thread, self.workers.evaluate, weights.params, version,
                                                e.episodes, e.seeds, e.deterministic, video_dir, e.video_episodes)
        except concurrent.futures.process.BrokenProcessPool:
            raise  # a worker died: the service exits and the launcher starts it again
        except Exception as exc:  # the env or the policy failed on this version: reported, the next one may do
            self.log.exception("evaluation of v%d failed", version)
            self.count("eval/failures")
            self.event("eval", f"evaluation of v{version} failed: {type(exc).__name__}: {exc}")
            return
        finally:
            self.busy = False
        self.video_dir = None  # complete
        self.publish_span("eval", f"v{version}", start, time.time())
        self.evaluations += 1
        await self.publish_report(result.metrics())
        self.event("eval", describe_result(result))
        self.log.info("%s", describe_result(result))
        if self.best.better(result):
            await loop.run_in_executor(self.thread, self.save_best, weights.params, result)

    def save_best(self, params, result: EvalResult) -> None:
        load_arrays(self.model, params, source=f"weights v{result.version}")
        path = self.best.save(self.model, self.metadata, result)
        self.log.info("v%d is the best so far: %s", result.version, path)

    def metrics(self) -> dict[str, float]:
        out = {"eval/evaluations": float(self.evaluations), "eval/versions_skipped": float(self.schedule.skipped),
               "eval/busy": float(self.busy), "eval/newest_version": float(self.newest)}
        if self.best.version is not None:
            out["eval/best_version"] = float(self.best.version)
        return out

    async def teardown(self) -> None:
        self.workers.close()  # an evaluation in progress is dropped with its unfinished videos
        self.thread.shutdown(wait=False, cancel_futures=True)
        if self.video_dir and os.path.isdir(self.video_dir):
            for name in os.listdir(self.video_dir):
                if ".tmp." in name:
                    os.remove(os.path.join(self.video_dir, name))
            if not os.listdir(self.video_dir):
                os.rmdir(self.video_dir)


def describe_result(result: EvalResult) -> str:
    m = result.metrics()
    parts = [f"return {m['eval/return']:.1f}"]
    if "eval/success_rate" in m:
        parts.insert(0, f"success {m['eval/success_rate']:.0%} [{m['eval/success_rate_lo']:.0%}-"
                        f"{m['eval/success_rate_hi']:.0%}]")
    return (f"eval v{result.version}: " + ", ".join(parts) + f" over {len(result.episodes)} episodes "
            f"({result.seconds:.1f} s)")


def main() -> None:
    service_main(EvalService)


if __name__ == "__main__":
    main()
