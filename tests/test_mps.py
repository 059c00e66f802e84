"""The run's MPS control daemon: started only when none is reachable, quit only if this run started it.

NVIDIA's ``nvidia-cuda-mps-control`` is faked at its boundary: a script on PATH that makes and removes the
control pipe as the daemon does."""

from __future__ import annotations

import os
import stat

import pytest

from ebrl.resources import mps
from ebrl.resources.pool import ResourceError, mps_reachable

FAKE = """#!/bin/sh
if [ "$1" = "-d" ]; then
    [ -n "$FAIL" ] && { echo "cannot start: $FAIL" >&2; exit 1; }
    rm -f "$CUDA_MPS_PIPE_DIRECTORY/gone" "$CUDA_MPS_PIPE_DIRECTORY/control"
    mkfifo "$CUDA_MPS_PIPE_DIRECTORY/control" && echo started >> "$CUDA_MPS_LOG_DIRECTORY/control.log"
    exit 0
fi
read cmd
[ -e "$CUDA_MPS_PIPE_DIRECTORY/gone" ] && { echo "Cannot find MPS control daemon process"; exit 1; }
[ "$cmd" = quit ] && touch "$CUDA_MPS_PIPE_DIRECTORY/gone" && echo quit >> "$CUDA_MPS_LOG_DIRECTORY/control.log"
exit 0
"""  # like the real one, a daemon that quit leaves its control pipe behind


@pytest.fixture
def fake_control(tmp_path, monkeypatch):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    script = bin_dir / mps.CONTROL
    script.write_text(FAKE)
    script.chmod(script.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    return tmp_path


def test_a_daemon_is_started_when_none_runs_and_quit_at_the_end(fake_control):
    pipe, logs = fake_control / "pipe", fake_control / "logs"
    daemon = mps.MpsDaemon.ensure(logs, pipe_dir=str(pipe))
    assert daemon is not None and mps_reachable(str(pipe))
    assert daemon.quit() and not mps_reachable(str(pipe))
    assert (logs / "control.log").read_text().split() == ["started", "quit"]


def test_a_running_daemon_is_used_and_left_running(fake_control):
    pipe = fake_control / "pipe"
    pipe.mkdir()
    os.mkfifo(pipe / "control")  # someone else's daemon
    assert mps.MpsDaemon.ensure(fake_control / "logs", pipe_dir=str(pipe)) is None
    assert mps_reachable(str(pipe)) and not (fake_control / "logs").exists()


def test_a_pipe_a_quit_daemon_left_behind_is_not_a_daemon(fake_control):
    pipe, logs = fake_control / "pipe", fake_control / "logs"
    first = mps.MpsDaemon.ensure(logs, pipe_dir=str(pipe))
    assert first is not None and first.quit()
    assert (pipe / "control").exists() and not mps_reachable(str(pipe))  # the pipe stays, nobody answers
    second = mps.MpsDaemon.ensure(logs, pipe_dir=str(pipe))  # so the next run starts its own
    assert second is not None and mps_reachable(str(pipe)) and second.quit()


def test_a_daemon_that_cannot_start_is_a_clear_error(fake_control, monkeypatch):
    monkeypatch.setenv("FAIL", "no GPU")
    with pytest.raises(ResourceError, match="-d failed .*cannot start: no GPU"):
        mps.MpsDaemon.ensure(fake_control / "logs", pipe_dir=str(fake_control / "pipe"))


def test_without_the_control_program_the_error_says_what_to_do(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(ResourceError, match="nvidia-cuda-mps-control is not on PATH.*gpu_pool = 'none'"):
        mps.MpsDaemon.ensure(tmp_path / "logs", pipe_dir=str(tmp_path / "pipe"))
