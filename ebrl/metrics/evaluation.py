"""The eval service's metrics (``eval/*``, [Evaluating](evaluation.md)): a report of its own for each evaluated
version (``ebrl.evaluate``), and periodic ones of what it did (``ebrl/services/eval.py``)."""

from __future__ import annotations

from ebrl.metric import Metric

RESULT = "evaluate.py"  # one report per evaluated version
SERVICE = "services/eval.py"

METRICS = (
    Metric("eval/version", "version", "the version the report evaluated (result reports only)", RESULT),
    Metric("eval/return", "return", "mean return of its `eval.episodes` episodes on the held-out seeds", RESULT),
    Metric("eval/return_lo", "return", "lower end of the mean return's 95 % t interval (two episodes or more)",
           RESULT),
    Metric("eval/return_hi", "return", "upper end of that interval", RESULT),
    Metric("eval/success_rate", "fraction", "success rate of those episodes (tasks with a success check)", RESULT),
    Metric("eval/success_rate_lo", "fraction", "lower end of its 95 % Wilson interval", RESULT),
    Metric("eval/success_rate_hi", "fraction", "upper end of that interval", RESULT),
    Metric("eval/episode_length", "steps", "mean episode length", RESULT),
    Metric("eval/episodes", "episodes", "episodes played", RESULT),
    Metric("eval/eval_s", "s", "seconds the evaluation took", RESULT),
    Metric("eval/evaluations", "evaluations", "evaluations done (periodic reports)", SERVICE),
    Metric("eval/versions_skipped", "versions", "due versions replaced by a newer one while an evaluation ran",
           SERVICE),
    Metric("eval/busy", "0/1", "1 while an evaluation runs", SERVICE),
    Metric("eval/newest_version", "version", "the newest version received", SERVICE),
    Metric("eval/best_version", "version", "the best version evaluated so far (success rate, then mean return): "
           "`RUN_DIR/best.safetensors`", SERVICE),
    Metric("eval/failures", "evaluations", "evaluations that failed (the env or the policy raised)", SERVICE,
           counter=True),
)
