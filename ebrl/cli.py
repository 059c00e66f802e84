"""``ebrl`` command line: up, eval, stats, sweep, profile, report, bench, router, secret, slurm, schemas, config,
configs, init, graph, libero.

Each command is two functions, ``_args_<command>`` (its arguments) and ``_run_<command>`` (what it does,
importing what it needs only then, so ``ebrl --help`` stays fast), listed once in :data:`COMMANDS`."""

from __future__ import annotations

import argparse
import sys


UP_EXAMPLES = """examples:
  ebrl up quickstart                        a stock config by name (`ebrl configs` lists them)
  ebrl up configs/my_run.toml --set run.iterations=50 --set train.lr=1e-4
  ebrl up quickstart --viz web              the live timeline in a browser
  ebrl up quickstart --resume runs/quickstart-20261129-101500
  ebrl up my_run.toml --host learner        one host of a run over several ([hosts] in the config)

It prints the run's directory first, then a progress line; the run ends at run.iterations,
run.target_return or run.target_success (Ctrl-C stops it cleanly). Config keys: `ebrl config`;
docs: README.md and docs/."""


def _args_up(p: argparse.ArgumentParser) -> None:
    p.description = ("Start a training run: every service of the config (simulators, generation, training, ...)\n"
                     "as its own process on this host, supervised until the run ends.")
    p.epilog = UP_EXAMPLES
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("config", help="a config file (TOML), or a stock config's name, e.g. quickstart")
    p.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE",
                   help="override one config value (TOML syntax), e.g. --set run.iterations=2")
    p.add_argument("--viz", nargs="?", const="spawn", default=None, choices=("spawn", "serve", "web", "save", "off"),
                   help="live rerun timeline: spawn a viewer (the default of a bare --viz), serve for a viewer "
                        "to connect, web (a browser's viewer on 127.0.0.1:viz.web_port), save "
                        "RUN_DIR/timeline.rrd, or off (sets viz.rerun)")
    p.add_argument("--only", default=None, metavar="SERVICES",
                   help="start only these services on this host (comma-separated, e.g. sim or gen,train): one "
                        "host of a run over several; the bus endpoints join the hosts")
    p.add_argument("--instance", type=int, default=None, metavar="N",
                   help="with --only: this host's number in the run (its sim is sim/N; give each host its own)")
    p.add_argument("--host", default=None, metavar="NAME",
                   help="start what [hosts.NAME] of the config says runs on this host")
    p.add_argument("--resume", default=None, metavar="RUN_DIR",
                   help="continue a stopped run in its directory, from its latest checkpoint (policy, optimizer, "
                        "version); run.iterations counts from the run's start")


def _run_up(args: argparse.Namespace) -> int:
    from ebrl.launch import up

    return up(args.config, args.overrides, viz=args.viz, resume=args.resume, only=args.only, host=args.host,
              instance=args.instance)


SWEEP_EXAMPLES = """examples:
  ebrl sweep examples/sweep_quickstart.toml              a sweep file: config, params, objective, budget
  ebrl sweep examples/sweep_quickstart.toml --jobs 2     two trials at once (default: one per 2 cores)
  ebrl sweep quickstart --param train.lr=log_uniform:1e-4,3e-3 --param algo.clip=uniform:0.1,0.3 \\
      --iterations 30 --trials 20                       a config swept by flags alone
  ebrl sweep examples/sweep_quickstart.toml --best -o best.toml   the best trial's config, for ebrl up
  ebrl sweep examples/sweep_quickstart.toml --storage postgresql://user@db/ebrl   several machines, one study

Each trial is a real `ebrl up` in SWEEP_DIR/trials/, pruned from its learning curve; Ctrl-C stops the trials
cleanly and running the sweep again goes on where it was. Results: SWEEP_DIR/results.md, results.csv, *.png.
Guide: docs/sweeps.md."""


def _args_sweep(p: argparse.ArgumentParser) -> None:
    p.description = ("Sweep hyperparameters with Optuna: each trial a real `ebrl up` of the config with the trial's\n"
                     "values, followed live and pruned from its curve; the study in a database (SQLite by default).")
    p.epilog = SWEEP_EXAMPLES
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("sweep", help="a sweep file (TOML with a top-level `config`), or a config (path or stock name) "
                                 "swept by --param")
    p.add_argument("--param", action="append", default=[], dest="params", metavar="KEY=DIST",
                   help="sweep a config key: KIND:ARGS (log_uniform:1e-4,3e-3, uniform:0.1,0.3, int:4,16[,step], "
                        "log_int:2,64, choice:a,b) or a TOML table ({log_uniform = [1e-4, 3e-3]})")
    p.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE",
                   help="a fixed config value for every trial, after the file's [set]")
    p.add_argument("--trials", type=int, default=None, help="trials to finish in the study (n_trials; a total over "
                                                            "every run of the sweep, every process)")
    p.add_argument("--jobs", type=int, default=None, help="trials at once on this host (0: one per cores_per_trial "
                                                          "cores, 2 by default)")
    p.add_argument("--iterations", type=int, default=None, help="each trial's run.iterations (budget.iterations)")
    p.add_argument("--metric", default=None, help="the objective metric (default train/episode_return_mean)")
    p.add_argument("--direction", default=None, choices=("maximize", "minimize"))
    p.add_argument("--study", default=None, help="the study's name (default: the sweep file's name)")
    p.add_argument("--storage", default=None, metavar="URL",
                   help="the study's database (default sqlite:///SWEEP_DIR/study.db; postgresql://... for several "
                        "machines)")
    p.add_argument("--dir", default=None, help="the sweep's directory (default sweeps/<study>)")
    p.add_argument("--best", action="store_true", help="print the best trial's config (TOML for ebrl up) and exit")
    p.add_argument("-o", "--output", default=None, metavar="FILE", help="with --best: write it here")
    p.add_argument("--report", action="store_true", help="only write the results table and plots from the study")


def _run_sweep(args: argparse.Namespace) -> int:
    try:
        import optuna  # noqa: F401 -- the sweep extra
    except ImportError:
        print("ebrl sweep needs Optuna: pip install 'ebrl[sweep]'", file=sys.stderr)
        return 2
    from ebrl.sweep.runner import command

    return command(args.sweep, params=args.params, sets=args.overrides, best=args.best, output=args.output,
                   report=args.report, n_trials=args.trials, jobs=args.jobs, storage=args.storage, study=args.study,
                   directory=args.dir, metric=args.metric, direction=args.direction, iterations=args.iterations)


def _args_eval(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="a run directory (its latest policy, or --best) or a .safetensors policy file")
    p.add_argument("--episodes", type=int, default=None,
                   help="episodes to run (default 10); with --suite: initial states per task (default 50, all)")
    p.add_argument("--seed", type=int, default=None,
                   help="reset seed of the first episode; episode i uses seed + i (default 2000000000: held out "
                        "from training's seeds, the same as the eval service's eval.seeds)")
    p.add_argument("--video", default=None, metavar="DIR",
                   help="record the first --video-episodes episodes to DIR (MP4, or GIF without an ffmpeg encoder)")
    p.add_argument("--video-episodes", type=int, default=3, metavar="N", help="episodes recorded with --video (3)")
    p.add_argument("--stochastic", action="store_true",
                   help="sample actions (default: deterministic, the Gaussian mean; flow: x0 = 0, no final noise)")
    p.add_argument("--best", action="store_true",
                   help="a run directory's best.safetensors (the eval service's best) instead of its latest policy")
    p.add_argument("--config", default=None, metavar="TOML",
                   help="the run's config.toml, for a policy file written before policies carried their config")
    p.add_argument("--out", default=None, metavar="FILE",
                   help="where to write eval.json (default: RUN_DIR/eval.json for a run directory, ./eval.json "
                        "for a file; with --suite eval_SUITE.json, and {suite} in FILE is the suite)")
    p.add_argument("--suite", action="append", default=[], metavar="SUITE",
                   help="the LIBERO protocol instead: every task of the suite (libero_spatial, libero_object, "
                        "libero_goal, libero_10, libero_90; repeat or comma-separate for several) from its official "
                        "initial states, in parallel envs; success per task and per suite with Wilson intervals")
    p.add_argument("--tasks", default=None, metavar="I,J",
                   help="with --suite: only these tasks (indices)")
    p.add_argument("--workers", type=int, default=0,
                   help="with --suite: env processes (default: one per CPU this process may use)")


def _run_eval(args: argparse.Namespace) -> int:
    if args.suite:
        from ebrl.evaluate_suite import command as suite_command

        suites = [s.strip() for item in args.suite for s in item.split(",") if s.strip()]
        tasks = [int(t) for t in args.tasks.split(",")] if args.tasks else None
        return suite_command(args.path, suites, episodes=args.episodes or 50, tasks=tasks, workers=args.workers,
                             stochastic=args.stochastic, best=args.best, config=args.config, out=args.out)
    from ebrl.evaluate import command

    return command(args.path, episodes=args.episodes or 10, seed=args.seed, video=args.video,
                   video_episodes=args.video_episodes, stochastic=args.stochastic, best=args.best,
                   config=args.config, out=args.out)


def _args_stats(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", nargs="?", default="",
                   help="the run's directory (or its bus.secret file): signs in with the run's secret and connects "
                        "to its launcher; omit for a run with bus.auth = false")
    p.add_argument("--run", default=None, help="only this run (default: every run)")
    p.add_argument("--connect", default=None,
                   help="bus endpoint of the run (its launcher; default: from RUN_DIR/bus.json, else "
                        "tcp/127.0.0.1:7447)")
    p.add_argument("--spans", action="store_true", help="also print timeline spans")
    p.add_argument("--count", type=int, default=0,
                   help="exit after this many messages (0: until the run ends, or Ctrl-C when following every run)")
    p.add_argument("--json", action="store_true", help="one JSON object per line (its key, then its fields)")


def _run_stats(args: argparse.Namespace) -> int:
    from ebrl.stats import command

    return command(args.connect, args.run, spans=args.spans, count=args.count, secret=args.run_dir,
                   as_json=args.json)


def _args_bench(p: argparse.ArgumentParser) -> None:
    p.add_argument("config")
    p.add_argument("--modes", default="ebrl,colocated,hybrid,async", help="comma-separated modes")
    p.add_argument("--ablations", action="store_true", help="add ebrl with each mechanism (allocator, group_pipeline, overlap, core_rebinding) "
                   "flipped from what the config runs")
    span = p.add_mutually_exclusive_group()
    span.add_argument("--duration", type=float, default=60.0, help="measured seconds per run (after warm-up)")
    span.add_argument("--trajectories", type=int, default=0,
                      help="measure each run until this many trajectory segments are done, instead of --duration")
    p.add_argument("--variant", action="append", default=[], metavar="LABEL=SECTION.KEY=VALUE[,...]",
                   help="add a variant: LABEL is a mode followed by + or - and a name (e.g. "
                   "hybrid+vectorized=sim.vectorized=true); it runs that mode with these overrides")
    p.add_argument("--repeat", type=int, default=1, help="rounds over all modes")
    p.add_argument("--json", default="", help="write the results here")
    p.add_argument("--raw-seconds", type=float, default=10.0,
                   help="seconds to measure the raw simulator capacity (the physical limit; 0 skips it)")
    p.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE")


def _run_bench(args: argparse.Namespace) -> int:
    from ebrl import bench

    return bench.main(args.config, args.modes, args.ablations, args.duration, args.repeat, args.json,
                      args.overrides, args.raw_seconds, args.trajectories, args.variant)


def _args_profile(p: argparse.ArgumentParser) -> None:
    p.add_argument("config")
    p.add_argument("--force", action="store_true", help="measure even if a fresh profile of this machine exists")
    p.add_argument("--seconds", type=float, default=None, help="seconds per grid point (default alloc.profile_seconds)")
    p.add_argument("--out", default=None, help="profile file (default alloc.profile_path or runs/profiles/<name>.json)")
    p.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE")


def _run_profile(args: argparse.Namespace) -> int:
    from ebrl.alloc.cli import profile_command

    return profile_command(args.config, args.overrides, force=args.force, seconds=args.seconds, out=args.out)


def _args_report(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", help="a run directory (holds stats.msgpack)")
    p.add_argument("--start", type=float, default=None, help="window start, seconds after the run's first record")
    p.add_argument("--end", type=float, default=None, help="window end, seconds after the run's first record")
    p.add_argument("--last", type=float, default=None, help="window: the last S seconds of the run")
    p.add_argument("--out", default=None, help="output directory (default RUN_DIR/report)")


def _run_report(args: argparse.Namespace) -> int:
    from ebrl.viz import report

    try:
        paths = report.write(args.run_dir, start=args.start, end=args.end, last=args.last, out=args.out)
    except (OSError, ValueError) as exc:
        print(f"ebrl: report: {exc}", file=sys.stderr)
        return 2
    for path in paths.values():
        print(path)
    return 0


def _args_router(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable; default tcp/127.0.0.1:7447; one other hosts can "
                        "reach must be tls/... unless --insecure)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="another router to join")
    p.add_argument("--config", default="", help="native Zenoh JSON5 config (TLS certificates); its listen "
                                                "endpoints are kept")
    p.add_argument("--secret", default="", metavar="FILE",
                   help="the run's shared secret (bus.secret_file of its hosts): only its holders may join")
    p.add_argument("--insecure", action="store_true", help="allow plain tcp endpoints beyond this host (warns)")
    p.add_argument("--quiet", action="store_true", help="do not print services joining and leaving")


def _run_router(args: argparse.Namespace) -> int:
    from ebrl.bus.router import serve

    return serve(args.listen or ["tcp/127.0.0.1:7447"], args.connect, args.config, args.quiet,
                 secret=args.secret, insecure=args.insecure)


def _args_secret(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="where to write it (mode 0600; an existing file is never replaced)")
    p.add_argument("--observer", default=None, metavar="RUN_DIR",
                   help="instead: a read-only file for the run in RUN_DIR (its observer's line alone, no service "
                        "password) to hand to another user or script: ebrl stats PATH --connect ENDPOINT")


def _run_secret(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from ebrl.bus import auth

    try:
        if args.observer is None:
            print(auth.create(args.path))
            return 0
        print(auth.write_observer(Path(args.observer) / auth.FILENAME, args.path))
    except (OSError, auth.AuthError) as exc:
        print(f"ebrl secret: {args.path}: {getattr(exc, 'strerror', None) or exc}", file=sys.stderr)
        return 2
    try:
        endpoint = json.loads((Path(args.observer) / "bus.json").read_text())["listen"][0]
    except (OSError, ValueError, KeyError, IndexError):
        endpoint = "ENDPOINT"
    print(f"read-only access to the run; give the file to its user (chown) and watch with: ebrl stats {args.path} "
          f"--connect {endpoint}")
    return 0


def _args_slurm(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="the run's config; over several nodes with a [hosts] table, one entry per node")
    p.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE",
                   help="override one config value in every node's `ebrl up`")
    p.add_argument("--nodes", type=int, default=None,
                   help="nodes to allocate (default: one per [hosts] entry, else 1)")
    p.add_argument("--partition", default="", help="the Slurm partition (#SBATCH --partition)")
    p.add_argument("--time", default="", dest="time_limit", help="the job's time limit (#SBATCH --time, e.g. 2:00:00)")
    p.add_argument("--output", default=None, metavar="FILE",
                   help="where to write the script (default: ebrl-<run.name>.sbatch here)")
    p.add_argument("--submit", action="store_true", help="submit it with sbatch and print the job id")


def _run_slurm(args: argparse.Namespace) -> int:
    import os
    import subprocess
    from pathlib import Path

    from ebrl import config, slurm

    try:
        cfg = config.load(args.config, args.overrides)
        nodes = args.nodes or max(1, len(cfg.hosts))
        script = slurm.batch_script(args.config, cfg, args.overrides, nodes, args.partition, args.time_limit)
        path = Path(args.output or f"ebrl-{cfg.run.name}.sbatch")
        slurm.output_dir(cfg, os.getcwd()).mkdir(parents=True, exist_ok=True)  # Slurm opens its output there
        path.write_text(script)
        path.chmod(0o755)
        print(path)
        if args.submit:
            print(f"submitted: job {slurm.submit(path)}")
    except config.ConfigError as exc:
        print(f"ebrl slurm: config error: {exc}", file=sys.stderr)
        return 2
    except (OSError, subprocess.CalledProcessError) as exc:
        why = getattr(exc, "stderr", None) or getattr(exc, "strerror", None) or str(exc)
        print(f"ebrl slurm: {str(why).strip()}", file=sys.stderr)
        return 2
    return 0


def _args_schemas(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dir", default="schemas")


def _run_schemas(args: argparse.Namespace) -> int:
    from ebrl.messages import write_schemas

    for path in write_schemas(args.dir):
        print(path)
    return 0


def _args_config(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="config to validate and print resolved")
    p.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE")


def _run_config(args: argparse.Namespace) -> int:
    from ebrl import config

    if not args.config:
        print(config.describe())
        return 0
    try:
        print(config.dump_toml(config.load(args.config, args.overrides)), end="")
    except config.ConfigError as exc:
        print(f"ebrl: config error: {exc}", file=sys.stderr)
        return 2
    return 0


def _args_configs(p: argparse.ArgumentParser) -> None:
    pass


def first_sentence(text: str) -> str:
    """The first sentence of a config's opening comment (its lines joined, up to the first full stop)."""
    import re

    lines = []
    for line in text.splitlines():
        if not line.startswith("#") or line.startswith("#  "):  # the comment ends, or an indented example begins
            break
        lines.append(line.lstrip("#").strip())
    joined = " ".join(lines)
    found = re.search(r"^(.*?[.])(\s|$)", joined)
    return found.group(1) if found else joined


def _run_configs(args: argparse.Namespace) -> int:
    import shutil
    import textwrap

    from ebrl import config

    width = max(60, shutil.get_terminal_size((100, 24)).columns)
    for name, path in config.stock_configs().items():
        print(textwrap.fill(first_sentence(path.read_text()), width, initial_indent=f"{name:<26} ",
                            subsequent_indent=" " * 27, break_on_hyphens=False))
    return 0


def _args_init(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help="a stock config (ebrl configs lists them)")
    p.add_argument("dir", nargs="?", default=".", help="where to write it (and the configs it is based on)")


def _run_init(args: argparse.Namespace) -> int:
    from ebrl import config

    try:
        written = config.copy_stock(args.name, args.dir)
    except (config.ConfigError, OSError) as exc:
        print(f"ebrl init: {exc}", file=sys.stderr)
        return 2
    for path in written:
        print(path)
    print(f"edit it, then: ebrl up {written[0]}")
    return 0


def _args_libero(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=("setup", "tasks"),
                   help="setup: install what is missing of LIBERO (the libero extra, LIBERO itself without its "
                        "dependencies), link its assets, write its config; tasks: list a suite's tasks")
    p.add_argument("suite", nargs="?", default="libero_spatial", help="tasks: the suite (default libero_spatial)")


def _run_libero(args: argparse.Namespace) -> int:
    import subprocess

    from ebrl.envs import libero_suite

    try:
        if args.action == "setup":
            libero_suite.setup()
            print("LIBERO is ready: env.backend = \"libero\" (configs/libero_spatial.toml)")
        else:
            for task in libero_suite.tasks_of(args.suite):
                print(f"{task.index:>3}  {task.language}")
    except (ValueError, libero_suite.LiberoMissing, OSError, subprocess.CalledProcessError) as exc:
        print(f"ebrl libero: {exc}", file=sys.stderr)
        return 2
    return 0


def _args_graph(p: argparse.ArgumentParser) -> None:
    p.add_argument("--markdown", action="store_true", help="as docs/graph.md (a Mermaid chart and a table)")


def _run_graph(args: argparse.Namespace) -> int:
    from ebrl import graph

    print(graph.markdown() if args.markdown else graph.text(), end="")
    return 0


COMMANDS = {  # name: (help, its arguments, what it runs)
    "up": ("start a training run from a TOML config", _args_up, _run_up),
    "eval": ("evaluate a trained policy on held-out seeds: a table, eval.json, videos", _args_eval, _run_eval),
    "stats": ("print decoded ebrl/stats/** messages live", _args_stats, _run_stats),
    "sweep": ("sweep hyperparameters with Optuna: real ebrl up trials, pruned from their curves", _args_sweep,
              _run_sweep),
    "bench": ("run a config in several modes, interleaved, and compare throughput", _args_bench, _run_bench),
    "profile": ("profile each stage alone and print the tables and Algorithm 1's allocation", _args_profile,
                _run_profile),
    "report": ("write a run's Gantt PNG, throughput PNG and report.md from its recording", _args_report, _run_report),
    "router": ("run a Zenoh router that the hosts of a multi-host run connect to", _args_router, _run_router),
    "secret": ("create a secret file for a run over several hosts (bus.secret_file), or --observer: a read-only one",
               _args_secret, _run_secret),
    "slurm": ("write (and --submit) a Slurm batch script: one `ebrl up` per node", _args_slurm, _run_slurm),
    "schemas": ("write schemas/*.json from ebrl/messages/", _args_schemas, _run_schemas),
    "config": ("check a config, or list every config key", _args_config, _run_config),
    "configs": ("list the stock configs (ebrl up NAME runs one)", _args_configs, _run_configs),
    "init": ("copy a stock config here to edit", _args_init, _run_init),
    "graph": ("print the service graph: who publishes, subscribes to and queries what", _args_graph, _run_graph),
    "libero": ("set up the LIBERO benchmark (ebrl libero setup), or list a suite's tasks", _args_libero,
               _run_libero),
}


def parser() -> argparse.ArgumentParser:
    """``ebrl``'s argument parser: one sub-command per entry of :data:`COMMANDS`."""
    from ebrl import __version__

    out = argparse.ArgumentParser(prog="ebrl", description="Asynchronous embodied RL over a Zenoh bus.")
    out.add_argument("--version", action="version", version=f"ebrl {__version__}")
    sub = out.add_subparsers(dest="command", required=True)
    for name, (text, add_arguments, _) in COMMANDS.items():
        add_arguments(sub.add_parser(name, help=text))
    return out


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    return COMMANDS[args.command][2](args)


if __name__ == "__main__":
    sys.exit(main())
