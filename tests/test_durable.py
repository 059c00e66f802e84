"""Durable training state: a train killed while writing a checkpoint or handing segments over restarts from what
is readable, with no version reused and no segment trained on twice (real kill -9 of a writing process, and
files cut short as a kill leaves them)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest
import torch

from ebrl.algos import checkpoint
from ebrl.algos.handover import HANDOVER_FILE, HANDOVER_MAGIC, read_records
from ebrl.algos.learner import Learner
from ebrl.config import Config, PolicySection
from ebrl.envs import EnvSpec, ObsLayout, describe
from ebrl.messages import TrajectorySegment, encode_message
from ebrl.policies import make_policy
from helpers import ROOT

CFG = Config()  # the default env: InvertedPendulum-v5
INFO = describe(EnvSpec.from_config(CFG.env))

# Writes checkpoints v<start+1>, v<start+2>, ... as fast as it can, every weight equal to the version (so a
# restore that mixed two checkpoints would show), and prints each version once its save returned.
WRITER = textwrap.dedent("""
    import sys, torch
    from ebrl.algos import checkpoint
    from ebrl.config import PolicySection
    from ebrl.envs import ObsLayout
    from ebrl.policies import make_policy
    run_dir, version = sys.argv[1], int(sys.argv[2])
    model = make_policy(PolicySection(kind="mlp", chunk=2, hidden=[256, 256]), ObsLayout.vector(8), 2)
    optimizer = torch.optim.Adam(model.parameters())
    print("ready", flush=True)
    while True:
        version += 1
        with torch.no_grad():
            for p in model.parameters():
                p.fill_(version)
        checkpoint.save(run_dir, model, optimizer, version, {})
        print(version, flush=True)
""")


def wait_saved(proc: subprocess.Popen, count: int) -> list[int]:
    """Read the writer's lines until ``count`` versions were saved (a writer that dies ends the output)."""
    saved: list[int] = []
    while len(saved) < count:
        line = proc.stdout.readline()
        assert line, f"the writer exited ({proc.wait()})"
        if line.strip().isdigit():
            saved.append(int(line))
    return saved


def test_kill_9_while_writing_checkpoints_leaves_a_readable_one_no_older_than_the_last_saved(tmp_path):
    newest = 0
    for round, delay in enumerate((0.0, 0.003, 0.011, 0.029)):  # lands anywhere in a write
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path), str(newest)], cwd=ROOT,
                                stdout=subprocess.PIPE, text=True)
        try:
            saved = wait_saved(proc, 3 + round)
            time.sleep(delay)
            proc.send_signal(signal.SIGKILL)
            saved += [int(line) for line in proc.stdout.read().split() if line.isdigit()]  # what it printed last
        finally:
            proc.kill()
            proc.wait(30)
            proc.stdout.close()
        model = make_policy(PolicySection(kind="mlp", chunk=2, hidden=[256, 256]), ObsLayout.vector(8), 2)
        restored = checkpoint.restore_latest(tmp_path, model, torch.optim.Adam(model.parameters()), {})
        assert restored is not None and not restored.skipped
        assert saved[-1] <= restored.version <= restored.newest <= saved[-1] + 1  # at most the one being written
        assert all(bool((p == restored.version).all()) for p in model.parameters())  # one checkpoint, whole
        newest = restored.newest  # the next writer goes on past every version on disk, as a restarted train
    assert newest >= 3 + 4 + 5 + 6


def learner(run_dir) -> Learner:
    telemetry = SimpleNamespace(count=lambda *a: None, publish_span=lambda *a: None)
    return Learner(CFG, INFO, 4, telemetry, str(run_dir))


def test_a_train_restarted_after_a_torn_checkpoint_goes_on_from_the_previous_one_and_never_reuses_a_version(tmp_path):
    first = learner(tmp_path)
    for version in (10, 20):
        first.version = version
        with torch.no_grad():
            first.model.log_std.fill_(version / 100)
        assert first.save_checkpoint("r")
    train_state = tmp_path / "checkpoints" / "v00000020" / "train.safetensors"
    train_state.write_bytes(train_state.read_bytes()[:100])  # v20's disk lost the end of it
    (tmp_path / "checkpoints" / "v00000030.tmp").mkdir()  # killed while writing v30
    (tmp_path / ".policy.safetensors.x1y2.tmp").write_bytes(b"half")  # killed while writing policy.safetensors

    again = learner(tmp_path)
    assert again.resume(floor=-1) == "train resumed at policy v21 from v00000010"
    assert again.saved_version == 10 and float(again.model.log_std.detach()[0]) == pytest.approx(0.1)
    assert not list(tmp_path.glob("**/*.tmp"))
    assert again.save_checkpoint("r") and checkpoint.latest(tmp_path).name == "v00000021"

    launcher_saw = learner(tmp_path)  # the launcher saw v25 published: past that too
    assert launcher_saw.resume(floor=25) == "train resumed at policy v26 from v00000021"


def segments(model_learner: Learner, n: int) -> list[TrajectorySegment]:
    t, lrn = 3, model_learner
    return [TrajectorySegment(
        group=0, env_id=i, episode=0, obs=np.full((t, *lrn.obs_shape), i, np.float32),
        actions=np.zeros((t, *lrn.action_shape), np.float32), latents=np.zeros((t, *lrn.latent_shape), np.float32),
        logprobs=np.zeros(t, np.float32), values=np.zeros(t, np.float32), rewards=np.ones(t, np.float32),
        steps=np.ones(t, np.int32), versions=np.zeros(t, np.int64), end="cut",
        last_obs=np.zeros(lrn.obs_shape, np.float32), episode_returns=[], episode_lengths=[]) for i in range(n)]


def handed_over(run_dir, n: int = 4) -> Learner:
    stopping = learner(run_dir)
    for seg in segments(stopping, n):
        assert stopping.accept(seg, pytest.fail)
    assert stopping.hand_over() == n
    return stopping


def taken_envs(run_dir) -> tuple[list[int], tuple[int, int]]:
    """Take over what is there with a new learner: the env ids of the segments it took, and (taken, handed)."""
    new = learner(run_dir)
    malformed: list[Exception] = []
    result = new.take_over(malformed.append)
    assert not malformed
    return [seg.env_id for seg in new.collector.segments()], result


def test_handed_over_segments_are_taken_over_once(tmp_path):
    handed_over(tmp_path)
    assert (tmp_path / HANDOVER_FILE).read_bytes().startswith(HANDOVER_MAGIC)
    assert taken_envs(tmp_path) == ([0, 1, 2, 3], (4, 4))
    assert taken_envs(tmp_path) == ([], (0, 0))  # the file went before training: never trained on twice


@pytest.mark.parametrize("cut", [1, 7, 100, -1], ids=["record-header", "in-header", "in-payload", "last-byte"])
def test_a_torn_handover_file_loses_only_its_torn_record(tmp_path, cut, caplog):
    handed_over(tmp_path)
    path = tmp_path / HANDOVER_FILE
    data = path.read_bytes()
    payloads, torn = read_records(path)
    last_record = len(data) - len(payloads[-1]) - 8
    path.write_bytes(data[:last_record + cut] if cut > 0 else data[:cut])
    assert taken_envs(tmp_path) == ([0, 1, 2], (3, 3))
    assert "record 3 is torn" in caplog.text and not path.exists()


def test_garbage_after_the_records_is_ignored_and_a_garbled_record_ends_the_file(tmp_path, caplog):
    handed_over(tmp_path)
    path = tmp_path / HANDOVER_FILE
    data = path.read_bytes()
    path.write_bytes(data + os.urandom(3000))
    assert taken_envs(tmp_path)[0] == [0, 1, 2, 3]
    handed_over(tmp_path)
    payloads, _ = read_records(path)
    flipped = bytearray(data)
    flipped[len(data) - len(payloads[-1]) // 2] ^= 0xFF  # a bad byte inside the last record
    path.write_bytes(bytes(flipped))
    assert taken_envs(tmp_path) == ([0, 1, 2], (3, 3))
    assert "record 3 is garbled (checksum mismatch)" in caplog.text


def test_a_train_killed_while_handing_over_leaves_its_whole_records_to_the_next(tmp_path):
    """Killed in the middle of writing: only the temporary file is there, cut short; its whole records are
    taken over (they were never trained on), and both files go."""
    handed_over(tmp_path)
    path = tmp_path / HANDOVER_FILE
    tmp = path.with_name(f".{path.name}.k1l2.tmp")  # ebrl.durable's temporary, as a kill leaves it
    data = path.read_bytes()
    path.unlink()
    tmp.write_bytes(data[:len(data) - 5])
    assert taken_envs(tmp_path) == ([0, 1, 2], (3, 3))
    assert not tmp.exists() and not path.exists()


def test_a_handover_file_of_the_older_format_is_still_taken_over(tmp_path):
    stopping = learner(tmp_path)
    (tmp_path / HANDOVER_FILE).write_bytes(msgpack.packb([encode_message(s) for s in segments(stopping, 2)]))
    assert taken_envs(tmp_path) == ([0, 1], (2, 2))
    (tmp_path / HANDOVER_FILE).write_bytes(b"\x93garbage")
    assert taken_envs(tmp_path) == ([], (0, 0))
