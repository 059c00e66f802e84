"""The weights a learner makes from fixed segments, as a hash: run at two commits, equal hashes say a change left
the algorithm's updates bit-identical (issue 53 moved PPO and GRPO behind the algorithm interface).

    python benchmarks/learner_parity.py quickstart            # PPO: 3 updates of 256 decisions
    python benchmarks/learner_parity.py grpo_pendulum         # GRPO
    git worktree add /tmp/base 9ce5426 && (cd /tmp/base && PYTHONPATH=. python $OLDPWD/benchmarks/learner_parity.py quickstart)

Segments of random observations, actions and rewards (seeded), acted by the learner's own versions, whole
episodes (GRPO groups them); the learner as the train service drives it (accept, take, update).
"""
import hashlib, sys, tempfile
from types import SimpleNamespace
import numpy as np, torch
from ebrl.algos.learner import Learner
from ebrl.config import load
from ebrl.envs import EnvSpec, describe
from ebrl.messages import TrajectorySegment
from ebrl.policies import state_arrays
name = sys.argv[1]
cfg = load(name, ["train.batch_size=256"])
info = describe(EnvSpec.from_config(cfg.env))
K, A = cfg.policy.chunk, info.action_dim
rng = np.random.default_rng(0)
tel = SimpleNamespace(count=lambda *a: None, publish_span=lambda *a: None)
with tempfile.TemporaryDirectory() as d:
    learner = Learner(cfg, info, 1, tel, d)
    learner.resume(-1)
    for it in range(3):
        for env in range(8):
            t = 32
            rewards = rng.uniform(0, K, t).astype(np.float32)
            seg = TrajectorySegment(group=0, env_id=env, episode=it, obs=rng.normal(size=(t, *info.obs_shape)).astype(np.float32),
                actions=rng.normal(size=(t, K, A)).astype(np.float32), latents=np.zeros((t, 0), np.float32),
                logprobs=rng.normal(size=t).astype(np.float32) - 3, values=rng.normal(size=t).astype(np.float32),
                rewards=rewards, steps=np.full(t, K, np.int32),
                versions=np.full(t, learner.version, np.int64), end="terminated", last_obs=rng.normal(size=info.obs_shape).astype(np.float32),
                episode_returns=[float(rewards.astype(np.float64).sum())], episode_lengths=[t * K])
            learner.accept(seg, print)
        while learner.ready:
            out = learner.update(learner.take())
    out = locals().get("out", {})
    h = hashlib.sha256(b"".join(a.tobytes() for _, a in sorted(state_arrays(learner.model).items()))).hexdigest()[:16]
    print(name, "v", learner.version, "weights", h, "policy_loss", out.get("policy_loss"))
