"""A real single-node Slurm cluster for the tests (Debian's slurmctld, slurmd and munge): started as root with a
config of its own in a temporary directory, shut down after."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from pathlib import Path

DAEMONS = ("slurmctld", "slurmd", "munged", "sbatch", "srun", "scontrol")


def unavailable() -> str | None:
    missing = [d for d in DAEMONS if shutil.which(d) is None]
    if missing:
        return f"Slurm is not installed ({', '.join(missing)} missing: apt-get install slurmd slurmctld slurm-client munge)"
    if os.geteuid() != 0:
        return "starting Slurm's daemons needs root"
    return None


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _munge_works() -> bool:
    try:
        encoded = subprocess.run(["munge", "-n"], capture_output=True, timeout=10)
        return encoded.returncode == 0 and subprocess.run(["unmunge"], input=encoded.stdout, capture_output=True,
                                                          timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


class Cluster:
    """``env``: the environment that points Slurm's commands at this cluster (``SLURM_CONF``)."""

    def __init__(self, where: Path):
        self.where = where
        for sub in ("state", "spool", "log"):
            (where / sub).mkdir(parents=True, exist_ok=True)
        self.munged: subprocess.Popen | None = None
        if not _munge_works():
            Path("/run/munge").mkdir(parents=True, exist_ok=True)
            shutil.chown("/run/munge", "munge", "munge")
            subprocess.run(["runuser", "-u", "munge", "--", "munged"], check=True, capture_output=True)
            self.munged = True  # type: ignore[assignment]
        node = socket.gethostname()
        conf = where / "slurm.conf"
        conf.write_text("\n".join([
            "ClusterName=ebrltest", f"SlurmctldHost={node}(127.0.0.1)", "SlurmUser=root", "SlurmdUser=root",
            "AuthType=auth/munge", f"StateSaveLocation={where / 'state'}", f"SlurmdSpoolDir={where / 'spool'}",
            f"SlurmctldPidFile={where / 'slurmctld.pid'}", f"SlurmdPidFile={where / 'slurmd.pid'}",
            f"SlurmctldLogFile={where / 'log' / 'slurmctld.log'}", f"SlurmdLogFile={where / 'log' / 'slurmd.log'}",
            f"SlurmctldPort={_free_port()}", f"SlurmdPort={_free_port()}", "ProctrackType=proctrack/linuxproc",
            "TaskPlugin=task/none", "JobAcctGatherType=jobacct_gather/none", "SelectType=select/cons_tres",
            "SelectTypeParameters=CR_Core", "ReturnToService=2", "MpiDefault=none",
            f"NodeName={node} NodeAddr=127.0.0.1 CPUs={os.cpu_count()} RealMemory=1000 State=UNKNOWN",
            "PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP", ""]))
        repo = str(Path(__file__).resolve().parent.parent)  # the jobs import this checkout's ebrl
        self.env = {**os.environ, "SLURM_CONF": str(conf),
                    "PYTHONPATH": os.pathsep.join(filter(None, [repo, os.environ.get("PYTHONPATH")]))}
        subprocess.run(["slurmctld", "-f", str(conf)], check=True, env=self.env, capture_output=True)
        subprocess.run(["slurmd", "-f", str(conf)], check=True, env=self.env, capture_output=True)
        deadline = time.monotonic() + 60
        while "idle" not in self.run("sinfo", "-h", "-o", "%T").stdout:
            if time.monotonic() > deadline:
                raise RuntimeError(f"Slurm's node did not come up: {(where / 'log' / 'slurmd.log').read_text()}")
            time.sleep(0.5)

    def run(self, *cmd: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
        return subprocess.run(list(cmd), env=self.env, capture_output=True, text=True, cwd=cwd)

    def wait_job(self, job: str, timeout: float) -> str:
        """The job's final state (COMPLETED, FAILED, ...), waiting for it at most ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            shown = self.run("scontrol", "show", "job", job, "-o").stdout
            state = shown.split("JobState=")[1].split()[0] if "JobState=" in shown else ""
            if state and state not in ("PENDING", "RUNNING", "CONFIGURING", "COMPLETING"):
                return state
            time.sleep(1.0)
        self.run("scancel", job)
        return "TIMEOUT (the test's)"

    def close(self) -> None:
        self.run("scontrol", "shutdown")
        for pid_file in ("slurmctld.pid", "slurmd.pid"):
            try:
                os.kill(int((self.where / pid_file).read_text()), 15)
            except (OSError, ValueError):
                pass
        if self.munged:
            subprocess.run(["pkill", "-x", "munged"], capture_output=True)
