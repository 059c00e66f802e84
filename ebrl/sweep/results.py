"""A sweep's results in its directory: the trials table (``results.csv``, ``results.md``), the plots (PNG through
``optuna.visualization.matplotlib``: no browser), the lines ``ebrl sweep`` prints, and the best trial's config as
a file ``ebrl up`` takes (``ebrl sweep SWEEP --best``)."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import warnings
from pathlib import Path
from typing import Any

import optuna
from optuna.trial import TrialState

from ebrl import config as config_mod
from ebrl.sweep.spec import Sweep, SweepError

IMPORTANCE_MIN = 3  # complete trials before parameter importance means anything (PED-ANOVA's top quantile)
PLOTS = (  # file, what it shows, the complete trials it needs
    ("history.png", "optimisation history", 1),
    ("curves.png", "learning curves (the objective at each training update; pruned ones stop early)", 0),
    ("importance.png", "parameter importance", IMPORTANCE_MIN),
)


def format_value(value: Any) -> str:
    if isinstance(value, float):
        return "" if math.isnan(value) else f"{value:.4g}"
    return "" if value is None else str(value)


def format_params(values: dict[str, Any]) -> str:
    return " ".join(f"{key}={format_value(value)}" for key, value in values.items())


def counts_line(study: optuna.Study) -> str:
    trials = study.get_trials(deepcopy=False)
    by = {state: sum(t.state == state for t in trials) for state in TrialState}
    return (f"{by[TrialState.COMPLETE] + by[TrialState.PRUNED]} finished ({by[TrialState.COMPLETE]} complete, "
            f"{by[TrialState.PRUNED]} pruned), {by[TrialState.FAIL]} failed, {by[TrialState.RUNNING]} running, "
            f"{by[TrialState.WAITING]} queued")


def header(sweep: Sweep, study: optuna.Study, jobs: int) -> str:
    """What ``ebrl sweep`` says first: the sweep, where it is kept, and how far its study is."""
    params = ", ".join(f"{p.key} {p.describe()}" for p in sweep.params)
    return (f"sweep {sweep.study}: {sweep.n_trials} trial{'s' * (sweep.n_trials != 1)} of {sweep.config}, {sweep.objective.describe()}; {params}\n"
            f"  {jobs} at once here; storage {sweep.storage}; directory {sweep.directory}\n"
            f"  the study so far: {counts_line(study)}")


def best_of(study: optuna.Study) -> optuna.trial.FrozenTrial | None:
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    return study.best_trial if complete else None


def trial_line(number: int, outcome: Any, sweep: Sweep, study: optuna.Study) -> str:
    """One line per ended trial, with the study's best so far."""
    best = best_of(study)
    tail = f"; best: trial {best.number}, {format_value(best.value)}" if best is not None else ""
    value = format_value(outcome.value)
    if outcome.state == "complete":
        return f"trial {number} complete: {sweep.objective.metric} = {value} at update {outcome.step}{tail}"
    if outcome.state == "pruned":
        return f"trial {number} {outcome.reason}: {value}{tail}"
    return f"trial {number} {'failed' if outcome.state == 'failed' else 'stopped'}: {outcome.reason}"


def rows(study: optuna.Study, sweep: Sweep) -> list[dict[str, Any]]:
    """One row per trial: number, state, each param's value, objective, last training update reported, seconds,
    run directory, the worker (host:pid) that ran it, and a note (why it failed, where it was pruned)."""
    out = []
    for t in study.get_trials(deepcopy=False):
        row: dict[str, Any] = {"trial": t.number, "state": t.state.name.lower()}
        for p in sweep.params:
            row[p.key] = t.params.get(p.key, "")
        value = t.value if t.state == TrialState.COMPLETE else (
            t.intermediate_values[max(t.intermediate_values)] if t.intermediate_values else None)
        row.update(objective=value, update=max(t.intermediate_values, default=""),
                   seconds=t.user_attrs.get("seconds", ""), run_dir=t.user_attrs.get("run_dir", ""),
                   worker=t.user_attrs.get("worker", ""),
                   note=t.user_attrs.get("failure") or t.user_attrs.get("note") or (
                       f"retry of trial {t.user_attrs['retry_of']}" if "retry_of" in t.user_attrs else ""))
        out.append(row)
    return out


def csv_text(table: list[dict[str, Any]], columns: list[str]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(table)
    return buffer.getvalue()


def markdown_table(table: list[dict[str, Any]], columns: list[str], directory: Path) -> str:
    def cell(key: str, value: Any) -> str:
        if key == "run_dir" and value:
            path = Path(value)
            with_in = directory.resolve()
            value = os.path.relpath(path, with_in) if path.is_absolute() and with_in in path.parents else value
        return format_value(value).replace("|", "\\|").replace("\n", " ")

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(key, row[key]) for key in columns) + " |" for row in table]
    return "\n".join(lines) + "\n"


def write_table(study: optuna.Study, sweep: Sweep, notes: list[str] | None = None) -> list[Path]:
    """``results.csv`` and ``results.md`` in the sweep's directory (the plots that exist, and ``notes`` on the
    ones that could not be drawn, linked from the Markdown)."""
    table = rows(study, sweep)
    columns = ["trial", "state", *(p.key for p in sweep.params), "objective", "update", "seconds", "run_dir",
               "worker", "note"]
    csv_path, md_path = sweep.directory / "results.csv", sweep.directory / "results.md"
    csv_path.write_text(csv_text(table, columns))
    best = best_of(study)
    lines = [f"# Sweep {sweep.study}", "",
             f"{sweep.config}: {sweep.objective.describe()}; {sweep.n_trials} trials. The study: {counts_line(study)} "
             f"(storage `{sweep.storage}`).", ""]
    if best is not None:
        lines += [f"Best: trial {best.number}, {format_value(best.value)}: {format_params(best.params)} "
                  "(`ebrl sweep SWEEP --best -o best.toml` writes its config).", ""]
    lines += [markdown_table(table, columns, sweep.directory), "## Plots", ""]
    for file, what, _ in PLOTS:
        if (sweep.directory / file).is_file():
            lines += [f"![{what}]({file})", ""]
    lines += [f"- {note}" for note in notes or ()]
    md_path.write_text("\n".join(lines).rstrip() + "\n")
    return [csv_path, md_path]


def write_plots(study: optuna.Study, sweep: Sweep) -> tuple[list[Path], list[str]]:
    """The PNG plots of :data:`PLOTS` that the study's trials allow, and a note for each that they do not (too few
    complete trials: a note, never an error)."""
    import matplotlib

    matplotlib.use("Agg")  # files only: no display needed
    import matplotlib.pyplot as plt
    from optuna.visualization import matplotlib as plots

    complete = len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)))
    curves = any(t.intermediate_values for t in study.get_trials(deepcopy=False))
    draw = {"history.png": plots.plot_optimization_history, "curves.png": plots.plot_intermediate_values,
            "importance.png": plots.plot_param_importances}
    written, notes = [], []
    verbosity = optuna.logging.get_verbosity()
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    try:
        for file, what, least in PLOTS:
            path = sweep.directory / file
            path.unlink(missing_ok=True)
            if complete < least or (file == "curves.png" and not curves):
                notes.append(f"{what}: needs at least {max(least, 1)} complete trial{'s' * (least > 1)} "
                             f"({complete} so far)" if file != "curves.png" else f"{what}: no trial reported one yet")
                continue
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                    axes = draw[file](study)
            except (ValueError, RuntimeError) as exc:
                notes.append(f"{what}: not drawn ({exc})")
                continue
            figure = getattr(axes, "figure", None) or axes.flat[0].figure
            figure.savefig(path, dpi=110, bbox_inches="tight")
            plt.close(figure)
            written.append(path)
    finally:
        optuna.logging.set_verbosity(verbosity)
    return written, notes


def write_all(study: optuna.Study, sweep: Sweep) -> list[str]:
    """The plots, then the tables; the lines to print (each file, each note)."""
    written, notes = write_plots(study, sweep)
    files = write_table(study, sweep, notes)
    return [f"results: {counts_line(study)}", *(f"  {path}" for path in [*files, *written]),
            *(f"  ({note})" for note in notes)]


def best_config(study: optuna.Study, sweep: Sweep) -> str:
    """The best complete trial's config, as TOML ``ebrl up`` takes: the sweep's config with its ``[set]`` and the
    trial's params applied, resolved (the budget left out: the config's own run length)."""
    best = best_of(study)
    if best is None:
        raise SweepError(f"study {sweep.study}: no complete trial yet ({counts_line(study)})")
    values = {p.key: p.value_of(best.params[p.key]) for p in sweep.params if p.key in best.params}
    try:
        cfg = config_mod.load(sweep.config, [*sweep.fixed, *(sweep.param(k).override(v) for k, v in values.items())])
    except config_mod.ConfigError as exc:
        raise SweepError(f"the best trial's config does not load: {exc}") from None
    budget = ", ".join(sweep.budget.overrides()) or "the config's own"
    head = [f"# The best trial of sweep {sweep.study}: trial {best.number}, {sweep.objective.metric} = "
            f"{format_value(best.value)} ({sweep.objective.describe()}, budget: {budget}).",
            f"# {sweep.config} with the sweep's [set] and these params: "
            + ", ".join(f"{k} = {json.dumps(v)}" for k, v in values.items()),
            "# Run it with `ebrl up FILE` (run.iterations is the config's own, not the sweep's budget)."]
    return "\n".join(head) + "\n\n" + config_mod.dump_toml(cfg)
