"""The MPS control daemon of a run: ``ebrl up`` starts one when its plan shares a GPU through MPS and none is
reachable, and quits it at the end — only a daemon it started; one that was already running is used and
left running. EBRL never changes a GPU's compute mode or MIG layout.

The daemon is NVIDIA's ``nvidia-cuda-mps-control -d``, given its pipe and log directories through
``CUDA_MPS_PIPE_DIRECTORY`` / ``CUDA_MPS_LOG_DIRECTORY``; it is quit by writing ``quit`` to the same program.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

from ebrl.resources.pool import MPS_CONTROL, MPS_PIPE_DEFAULT, ResourceError, mps_reachable

CONTROL = MPS_CONTROL
START_S = 10.0  # for the daemon's control pipe to appear
QUIT_S = 10.0  # for it to go away after "quit"


class MpsDaemon:
    """A daemon this run started (``ensure``); ``quit`` it when the run ends."""

    def __init__(self, pipe_dir: str, log_dir: str):
        self.pipe_dir, self.log_dir = pipe_dir, log_dir

    @property
    def env(self) -> dict[str, str]:
        return dict(os.environ, CUDA_MPS_PIPE_DIRECTORY=self.pipe_dir, CUDA_MPS_LOG_DIRECTORY=self.log_dir)

    @classmethod
    def ensure(cls, log_dir: str | os.PathLike, pipe_dir: str | None = None) -> "MpsDaemon | None":
        """None when a daemon is already reachable (it is used as it is); else start one and return it.
        ResourceError when the control program is missing or the daemon does not come up."""
        pipe_dir = pipe_dir or os.environ.get("CUDA_MPS_PIPE_DIRECTORY", MPS_PIPE_DEFAULT)
        if mps_reachable(pipe_dir):
            return None
        if shutil.which(CONTROL) is None:
            raise ResourceError(f"alloc.gpu_pool = 'mps' needs an MPS control daemon and {CONTROL} is not on PATH "
                                "(it comes with the NVIDIA driver); use alloc.gpu_pool = 'none' or 'mig'")
        daemon = cls(pipe_dir, str(log_dir))
        Path(pipe_dir).mkdir(parents=True, exist_ok=True)
        Path(log_dir).mkdir(parents=True, exist_ok=True)
        started = subprocess.run([CONTROL, "-d"], env=daemon.env, capture_output=True, text=True, timeout=START_S)
        if started.returncode != 0:
            raise ResourceError(f"{CONTROL} -d failed ({started.returncode}): {started.stderr.strip() or '-'}")
        deadline = time.monotonic() + START_S
        while not mps_reachable(pipe_dir):
            if time.monotonic() > deadline:
                raise ResourceError(f"{CONTROL} -d started, but no control pipe appeared in {pipe_dir} within "
                                    f"{START_S:.0f} s (see {log_dir}/control.log)")
            time.sleep(0.05)
        return daemon

    def quit(self) -> bool:
        """Quit the daemon (its clients have exited by now); True once its control pipe is gone."""
        try:
            subprocess.run([CONTROL], input="quit\n", env=self.env, capture_output=True, text=True, timeout=QUIT_S)
        except (OSError, subprocess.TimeoutExpired):
            return False
        deadline = time.monotonic() + QUIT_S
        while mps_reachable(self.pipe_dir):
            if time.monotonic() > deadline:
                return False
            time.sleep(0.05)
        return True
