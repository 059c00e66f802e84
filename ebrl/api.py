"""EBRL from Python: ``ebrl.train`` runs what ``ebrl up`` runs and returns the finished run.

::

    import ebrl
    run = ebrl.train("quickstart", run={"iterations": 20})
    print(run.summary["final_return"], run.policy_path)
    action, _ = run.load_policy().predict(obs)

The run is the same as from the command line: the launcher starts every service as its own process and
supervises them, printing its progress line; Ctrl-C stops every service and returns the run (exit code 130)
instead of leaving processes behind. ``ebrl.watch(run_dir)`` (:func:`ebrl.stats.stream`) follows a run from
another process, a thread, or a notebook cell.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any, Iterable, TextIO

from ebrl import config as config_mod


class RunNotStarted(RuntimeError):
    """The run could not start (a config error, a failed preflight); nothing was started."""


@dataclasses.dataclass
class TrainedRun:
    """A run ``ebrl.train`` finished or stopped: its directory and exit code (0: its iterations or target
    reached; 130: stopped by Ctrl-C; else it failed, and ``summary["failure"]`` says why)."""

    run_dir: Path
    exit_code: int

    @property
    def ok(self) -> bool:
        """Whether the run reached its iterations or target (exit code 0)."""
        return self.exit_code == 0

    @property
    def summary(self) -> dict[str, Any]:
        """``RUN_DIR/summary.json``: iterations, env steps, returns, restarts, failure."""
        return json.loads((self.run_dir / "summary.json").read_text())

    @property
    def policy_path(self) -> Path | None:
        """The trained policy, ``RUN_DIR/policy.safetensors`` (None where no version was trained)."""
        path = self.run_dir / "policy.safetensors"
        return path if path.exists() else None

    def load_policy(self, which: str = "latest", **kwargs: Any):
        """The run's policy to act with (:func:`ebrl.load_policy`; ``which="best"``: the eval service's best)."""
        from ebrl.policies.portable import load_policy

        return load_policy(self.run_dir, which=which, **kwargs)


def train(config: str | os.PathLike | config_mod.Config, *, overrides: Iterable[str] = (), resume: str | None = None,
          out: TextIO = sys.stdout, **sections: dict[str, Any]) -> TrainedRun:
    """Run a config to its end, as ``ebrl up`` does, and return the run.

    ``config``: a path, a stock config's name (``"quickstart"``, ``ebrl configs`` lists them) or a
    :class:`~ebrl.config.Config`. Changes come as sections of values (``run={"iterations": 2}``,
    ``env={"id": "Hopper-v5"}``) or as ``overrides`` in ``--set``'s form (``"run.iterations=2"``); ``resume``
    continues a stopped run in its directory. Raises :class:`RunNotStarted` where the run cannot start (the
    message names the field or the check); ``out`` gets the launcher's progress."""
    from ebrl import launch, prepare

    changes = [*overrides]
    for section, values in sections.items():
        if not isinstance(values, dict):
            raise TypeError(f"{section}={values!r}: a section's values as a dict, e.g. run={{'iterations': 2}}")
        changes += [config_mod.override(f"{section}.{key}", value) for key, value in values.items()]
    with tempfile.TemporaryDirectory(prefix="ebrl-config-") as tmp:
        path = str(config)
        if isinstance(config, config_mod.Config):
            path = os.path.join(tmp, "config.toml")
            Path(path).write_text(config_mod.dump_toml(config))
        try:
            prepared = prepare.prepare(path, changes, resume=resume)
        except prepare.NotStarted as exc:
            raise RunNotStarted(str(exc)) from None
    return TrainedRun(prepared.run_dir, launch.launch(prepared, out=out))
