"""What watches a run: ``[viz]``, ``[log]`` and ``[eval]``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ebrl.config.base import ConfigError, doc, Section


@dataclass
class VizSection(Section):
    NAME = "viz"
    POSITIVE = ("window_s", "port", "web_port")

    rerun: Literal["spawn", "serve", "web", "save", "off"] = doc(
        "live timeline in rerun: spawn a viewer, serve over gRPC for a viewer to connect (even late), web (serve "
        "rerun's web viewer to a browser, on 127.0.0.1:web_port), save only, or off (no viz service); every mode "
        "but off also writes RUN_DIR/timeline.rrd", "off")
    port: int = doc("gRPC port of the rerun server (serve, web; on 127.0.0.1) or of the spawned viewer (spawn)",
                    9876)
    web_port: int = doc("HTTP port of the web viewer's page (web), on 127.0.0.1; reach it from a laptop with "
                        "ssh -L web_port:127.0.0.1:web_port -L port:127.0.0.1:port HOST", 9090)
    memory_limit: str = doc("rerun server memory (serve, web): what a late viewer can still see", "2GiB")
    window_s: float = doc("seconds of history the live Gantt shows while following the present", 20.0)
    spans: bool = doc("publish timeline spans; false keeps only the busy/<lane> stats (for overhead measurements)",
                      True)
    record: bool = doc("record every stats report, span and event of the run to RUN_DIR/stats.msgpack (on the "
                       "primary host of several)", True)
    report: bool = doc("write RUN_DIR/report/ (Gantt PNG, throughput PNG, report.md) when the run ends", True)


@dataclass
class LogSection(Section):
    NAME = "log"
    POSITIVE = ("flush_s",)

    tensorboard: bool = doc("write RUN_DIR/tb/: TensorBoard event files of every metric, every episode's return and "
                            "success, eval results, the config (hparams) and the run's metadata, keyed by env steps "
                            "(open with `tensorboard --logdir runs/`)", True)
    csv: bool = doc("write RUN_DIR/metrics.csv: one row per value (step, wall_time, key, value), the same values "
                    "as TensorBoard", True)
    wandb: bool = doc("log to Weights & Biases (the optional extra: pip install 'ebrl[wandb]'); offline runs go to "
                      "RUN_DIR/wandb/ (upload later with `wandb sync`)", False)
    wandb_project: str = doc("W&B project", "ebrl")
    wandb_entity: str = doc("W&B entity (user or team); empty: your default", "")
    wandb_group: str = doc("W&B group of this run (e.g. a sweep or a seed set); empty: none", "")
    wandb_tags: list[str] = doc("W&B tags of this run", factory=list)
    wandb_mode: Literal["online", "offline"] = doc(
        "online (needs `wandb login` or WANDB_API_KEY, checked before the run starts) or offline (no account "
        "needed)", "online")
    exclude: list[str] = doc("metrics not written by any sink: shell patterns of metric names or of the keys "
                             "written, e.g. [\"cpu/*\", \"proc/*\", \"sim/busy/*\"]", factory=list)
    flush_s: float = doc("seconds between flushes of the sinks to disk", 5.0)


@dataclass
class EvalSection(Section):
    NAME = "eval"

    every: int = doc("evaluate every this many policy versions (v = every, 2 x every, ..., and the final version "
                     "of run.iterations) in the eval service; 0: no eval service. A version published while an "
                     "evaluation runs waits; a newer one replaces it (eval/versions_skipped)", 0)
    episodes: int = doc("episodes per evaluation", 10)
    seeds: int = doc("reset seed of the first evaluation episode; episode i resets with seeds + i, the same for "
                     "every version. The default is far from training's reset seeds (run.seed * 100003 + env + "
                     "7919 x episode), so evaluation runs on held-out initial states", 2_000_000_000)
    deterministic: bool = doc("deterministic actions (the Gaussian mean; flow: initial noise x0 = 0 and no noise at "
                              "the final step); false samples them", True)
    video_episodes: int = doc("episodes of each evaluation recorded to RUN_DIR/videos/v<version>/ (MP4, or GIF "
                              "without an ffmpeg encoder); 0: none", 1)
    cores: list[int] = doc("the eval service's cores: one env worker process pinned to each; empty: one worker on "
                           "any core. Always at idle priority (SCHED_IDLE), so it only takes CPU time training "
                           "leaves", factory=list)
    final_timeout: float = doc("seconds the launcher waits, once run.iterations are done, for the evaluation of "
                               "the final version (the other services idle meanwhile); 0: it does not wait", 300.0)

    def _check(self) -> None:
        if self.every < 0 or self.episodes < 1 or self.video_episodes < 0 or self.final_timeout < 0:
            raise ConfigError(f"[eval]: every ({self.every}), video_episodes ({self.video_episodes}) and "
                              f"final_timeout ({self.final_timeout}) must be >= 0 and episodes ({self.episodes}) >= 1")
        if not 0 <= self.seeds <= 2**32 - 1 - self.episodes:
            raise ConfigError(f"eval.seeds = {self.seeds}: must be in [0, 2^32 - 1 - eval.episodes] (simulators "
                              "take 32-bit seeds)")
