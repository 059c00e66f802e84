"""MuJoCo tasks on both engines: PandaPickCube on CPU MuJoCo (its gymnasium version), its simple model against the
full one, the MuJoCo Warp batch on Warp's CPU device against CPU MuJoCo, and `ebrl up` of the mjwarp config.

Warp compiles MuJoCo Warp's kernels on first use (15-60 s on 2 cores, once per machine: Warp's kernel cache keeps
them), so the batch is built once per module where it can be."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import pytest

from ebrl.config import ConfigError, load, vectorized
from ebrl.envs import EnvError, EnvSpec, describe, preflight
from ebrl.envs.mjtask import MjTaskEnv, task_class
from ebrl.envs.mjwarp import build
from ebrl.envs.tasks.pick_cube import HAND_HOME, HOME_QPOS, PandaPickCube
from helpers import up

ROOT = Path(__file__).resolve().parent.parent
warp = pytest.importorskip("warp", reason="MuJoCo Warp is the mjwarp extra: pip install -e '.[mjwarp]'")
torch = pytest.importorskip("torch")

SPEC = EnvSpec(id="PandaPickCube-v0", backend="mjwarp", kwargs={"device": "cpu"})
SEEDS = [2, 3, 4]  # episodes whose cube the scripted pick grasps squarely (on others it grazes an edge first)
# the observation's parts (PandaPickCube.observe)
GRIP, FINGERS, CUBE, TARGET = slice(0, 3), slice(3, 5), slice(7, 10), slice(17, 20)
ROBOT = np.r_[0:3, 23:30, 37:40]  # grip point, arm joints, hand target
ARM_VELOCITY = slice(30, 37)  # the arm's joint velocities (the fingers' chatter against the cube in a grasp)


def scripted(obs: np.ndarray, phase: list[int]) -> np.ndarray:
    """A pick-and-place by hand: above the cube, down to it, close, carry to the target (``phase`` is its state)."""
    grip, cube, target = obs[GRIP], obs[CUBE], obs[TARGET]
    action = np.zeros(4, np.float32)
    if phase[0] == 0:
        aim, action[3] = cube + (0, 0, 0.04), 1.0
        phase[0] += np.linalg.norm(aim - grip) < 0.01
    elif phase[0] == 1:
        aim, action[3] = cube + (0, 0, 0.01), 1.0
        phase[0] += np.linalg.norm(aim - grip) < 0.008
    elif phase[0] < 12:  # closing, 10 steps
        aim, action[3] = grip, -1.0
        phase[0] += 1
    else:
        aim, action[3] = target, -1.0
    action[:3] = np.clip((aim - grip) / 0.02, -1.0, 1.0)
    return action


@pytest.fixture(scope="module")
def batch():
    from ebrl.envs.batch import MjWarpBatch

    return MjWarpBatch(SPEC, SEEDS)


def cpu_envs(seeds):
    envs = [build(SPEC) for _ in seeds]
    return envs, np.stack([env.reset(seed=s)[0] for env, s in zip(envs, seeds)])


def test_the_cpu_version_is_a_registered_gymnasium_env_that_a_scripted_pick_solves():
    env = gym.make("ebrl.envs.tasks:PandaPickCube-v0")
    assert env.spec.max_episode_steps == PandaPickCube.max_episode_steps
    solved = 0
    for seed in range(4):
        obs, _ = env.reset(seed=seed)
        assert env.observation_space.contains(obs)
        phase, success = [0], False
        for _ in range(100):
            obs, reward, terminated, truncated, info = env.step(scripted(obs, phase))
            assert 0.0 <= reward <= 1.0 and not terminated  # the cube stays on the table or in the hand
            success = success or info["success"]
            if truncated:
                break
        assert truncated, "a success does not end the episode: holding the cube at the target is what pays"
        solved += success
    assert solved >= 3, "the scripted pick should hold the cube at the target"
    random = gym.make("ebrl.envs.tasks:PandaPickCube-v0")
    random.reset(seed=0)
    random.action_space.seed(0)
    successes = 0
    for _ in range(100):
        *_, info = random.step(random.action_space.sample())
        successes += info["success"]
    assert successes == 0


def test_the_hand_target_starts_where_the_hand_is():
    """HAND_HOME (where each episode's hand target starts) is the hand's position in the home pose."""
    task = PandaPickCube()
    data = mujoco.MjData(task.model)
    data.qpos[task.arm_qpos] = HOME_QPOS
    mujoco.mj_kinematics(task.model, data)
    hand = mujoco.mj_name2id(task.model, mujoco.mjtObj.mjOBJ_BODY, "hand")
    np.testing.assert_allclose(data.xpos[hand], HAND_HOME, atol=2e-3)


def rollout(model: str, seed: int, actions: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, bool]:
    """Observations of one episode on CPU MuJoCo under ``actions`` (or the scripted pick); the actions; success."""
    env = MjTaskEnv(PandaPickCube(model=model))
    obs, _ = env.reset(seed=seed)
    seen, taken, phase, success = [obs], [], [0], False
    for k in range(60 if actions is None else len(actions)):
        action = scripted(obs, phase) if actions is None else actions[k]
        obs, _, terminated, _, info = env.step(action)
        seen.append(obs)
        taken.append(action)
        success = success or info["success"]
        if terminated:
            break
    return np.stack(seen), np.stack(taken), success


def test_the_simple_model_moves_as_the_full_one_under_the_same_actions():
    """The simple model (no meshes; hand box and finger pads collide) against robosuite's meshes: in free space the
    arm's motion is the same (the bodies' inertia is explicit, so meshes change no mass); through a grasp and a
    lift under the full model's actions, the cube follows the same path to within a centimetre."""
    rng = np.random.default_rng(0)
    free = np.concatenate([rng.uniform(-1, 1, (40, 3)), np.ones((40, 1))], axis=1).astype(np.float32)
    free[:, 2] = np.abs(free[:, 2])  # upwards, away from the table and the cube
    full, _, _ = rollout("full", 3, free)
    simple, _, _ = rollout("simple", 3, free)
    np.testing.assert_allclose(simple[:, ROBOT], full[:, ROBOT], atol=1e-6)
    for seed in (2, 4, 6):
        full, actions, full_success = rollout("full", seed)
        simple, _, simple_success = rollout("simple", seed, actions)
        n = min(len(full), len(simple))
        assert full_success and simple_success, f"seed {seed}: the pick should succeed in both models"
        assert full[n - 1, CUBE][2] > 0.08, "the cube was lifted"
        np.testing.assert_allclose(simple[:n, CUBE], full[:n, CUBE], atol=0.01)


def test_the_warp_batch_agrees_with_cpu_mujoco_on_the_same_actions(batch):
    """Warp (float32) against MuJoCo's C engine (float64), 3 worlds: the same start from the same seeds, then the
    same actions (a scripted pick, contacts included): the arm's joints and the grip point within 5 mm (or mrad),
    the cube and the fingers within 2 mm, the arm's joint velocities within 3 % + 0.05, rewards within 0.01 until a
    success; every world succeeds on both, at the same step (give or take one). Measured at 4 mm, 0.2 mm, 0.07 and
    the same steps. (A grasp that grazes the cube's edge first, as on seeds 0, 1 and 5, parts the two by up to 2 cm
    in the cube's path: the engines' arithmetic differs most in contact, and a graze amplifies it.)"""
    obs = batch.reset(np.arange(3), np.zeros(3, np.int64)).cpu().numpy()
    envs, cpu = cpu_envs(SEEDS)
    np.testing.assert_allclose(obs, cpu, atol=1e-5)
    phases = [[0], [0], [0]]
    succeeded = {"warp": [None] * 3, "cpu": [None] * 3}
    for step in range(60):
        live = np.array([succeeded["warp"][i] is None and succeeded["cpu"][i] is None for i in range(3)])
        actions = np.stack([scripted(o, p) for o, p in zip(cpu, phases)])
        stepped = batch.step(torch.from_numpy(actions), torch.ones(3, dtype=torch.bool))
        outs = [env.step(a) if succeeded["cpu"][i] is None else (cpu[i], 0.0, True, False, {"success": True})
                for i, (env, a) in enumerate(zip(envs, actions))]
        cpu = np.stack([o[0] for o in outs])
        got = stepped.obs.cpu().numpy()
        for i in range(3):
            for engine, success in (("warp", bool(stepped.success[i])), ("cpu", outs[i][4]["success"])):
                if success and succeeded[engine][i] is None:
                    succeeded[engine][i] = step
        assert not (stepped.truncated.any() or any(o[3] for o in outs))
        np.testing.assert_allclose(got[live][:, ROBOT], cpu[live][:, ROBOT], atol=5e-3)
        np.testing.assert_allclose(got[live][:, CUBE], cpu[live][:, CUBE], atol=2e-3)
        np.testing.assert_allclose(got[live][:, FINGERS], cpu[live][:, FINGERS], atol=2e-3)
        np.testing.assert_allclose(got[live][:, ARM_VELOCITY], cpu[live][:, ARM_VELOCITY], rtol=0.03, atol=0.05)
        still = live & ~stepped.success.cpu().numpy() & ~np.array([o[4]["success"] for o in outs])
        np.testing.assert_allclose(stepped.reward.cpu().numpy()[still], np.array([o[1] for o in outs])[still],
                                   atol=1e-2)
        if all(s is not None for s in succeeded["warp"] + succeeded["cpu"]):
            break
    assert None not in succeeded["warp"] + succeeded["cpu"], succeeded
    assert max(abs(w - c) for w, c in zip(succeeded["warp"], succeeded["cpu"])) <= 1, succeeded


def test_a_partial_reset_starts_each_world_where_a_worker_with_its_seed_would(batch):
    before = batch.reset(np.arange(3), np.zeros(3, np.int64)).clone()
    after = batch.reset(np.array([1]), np.array([5])).numpy()
    _, cpu = cpu_envs([SEEDS[1] + 7919 * 5])  # world 1's seed, episode 5 (EPISODE_SEED_STRIDE)
    np.testing.assert_allclose(after[1], cpu[0], atol=1e-5)
    np.testing.assert_array_equal(after[[0, 2]], before.numpy()[[0, 2]])


def steps_alike(graphed, eager, atol: float) -> None:
    """``graphed`` and ``eager`` (the same worlds) under the same actions and partial resets: the same observations."""
    n, device = graphed.num_envs, graphed.device
    for b in (graphed, eager):
        b.reset(np.arange(n), np.zeros(n, np.int64))
    rng = np.random.default_rng(1)
    alive = torch.ones(n, dtype=torch.bool, device=device)
    for k in range(20):
        actions = torch.as_tensor(rng.uniform(-1, 1, (n, 4)), dtype=torch.float32, device=device)
        a, b = graphed.step(actions, alive), eager.step(actions, alive)
        torch.testing.assert_close(a.obs, b.obs, atol=atol, rtol=atol)
        if k % 7 == 6:  # world k % n starts its next episode: the reset's clearing and forward pass, graphed too
            idx, episodes = np.array([k % n]), np.array([k // 7 + 1])
            torch.testing.assert_close(graphed.reset(idx, episodes), eager.reset(idx, episodes), atol=atol, rtol=atol)


def test_on_the_cpu_too_the_steps_and_resets_replay_as_warp_graphs_and_land_where_eager_launches_do():
    """Warp replays a captured CPU graph without Python (2.4x an env step of 64 worlds on 2 cores: BENCHMARKS.md);
    graphed and eager batches must not part, through steps and partial resets."""
    from ebrl.envs.batch import MjWarpBatch

    graphed = MjWarpBatch(SPEC, SEEDS)
    eager = MjWarpBatch(EnvSpec(id="PandaPickCube-v0", backend="mjwarp", kwargs={"device": "cpu", "cuda_graph": False}),
                        SEEDS)
    assert graphed.graphed and not eager.graphed
    steps_alike(graphed, eager, atol=0.0)


def test_a_chunk_on_the_batch_keeps_each_worlds_episode_accounts():
    """BatchRunner over MuJoCo Warp worlds with a 6-step limit and chunks of 4: each world's second chunk ends its
    episode after 2 counted steps, truncated, with the return of its 6 rewards; the next chunk starts episode 1."""
    from ebrl.envs.batch import BatchRunner, MjWarpBatch

    spec = EnvSpec(id="PandaPickCube-v0", backend="mjwarp", max_episode_steps=6, kwargs={"device": "cpu"})
    runner = BatchRunner(MjWarpBatch(spec, [10, 11]))
    runner.reset(np.zeros(2, np.int64))
    actions = np.zeros((2, 4, 4), np.float32)
    first = runner.chunk(actions)
    second = runner.chunk(actions)
    assert list(first.steps) == [4, 4] and list(second.steps) == [2, 2]
    assert second.truncated.all() and not second.terminated.any()
    np.testing.assert_allclose(second.episode_return, first.reward + second.reward, rtol=1e-5)
    assert list(second.episode_length) == [6, 6] and list(second.episode_success) == [0, 0]
    assert list(runner.chunk(actions).episode) == [1, 1]


def test_a_world_that_diverges_ends_its_episode_and_the_others_go_on():
    """A user's task (tests/user_envs.py, named "module:Class") whose world 0 turns non-finite: that world's episode
    ends there as a truncation with reward 0 and a finite observation; world 1 is untouched."""
    from ebrl.envs.batch import MjWarpBatch

    sys.path.insert(0, str(Path(__file__).parent))
    spec = EnvSpec(id="user_envs:SlidingBlock", backend="mjwarp", kwargs={"device": "cpu", "explode_after": 2})
    batch = MjWarpBatch(spec, [0, 1])
    batch.reset(np.arange(2), np.zeros(2, np.int64))
    alive = torch.ones(2, dtype=torch.bool)
    for step in range(3):
        out = batch.step(torch.ones((2, 1)), alive)
    assert out.truncated.tolist() == [True, False] and out.reward[0] == 0 and torch.isfinite(out.obs).all()
    assert batch.unstable == 1


def test_the_default_buffers_hold_twice_what_pandapickcube_needs():
    """The contacts and constraint rows an mjwarp group allocates per world (env.kwargs.nconmax, njmax) against
    what the task uses with the hand pressed into the table and the cube by random actions, on CPU MuJoCo (the
    same colliders: measured 9 contacts and 44 rows at most over 60 episodes)."""
    from ebrl.envs.mjwarp import BATCH_KWARGS

    env = MjTaskEnv(PandaPickCube())
    rng = np.random.default_rng(0)
    contacts = rows = 0
    for episode in range(20):
        env.reset(seed=episode)
        for t in range(100):
            action = rng.uniform(-1, 1, (1, 4))
            action[0, 2] = -1.0 if t % 20 < 15 else 1.0  # mostly down, into the table or onto the cube
            env.task.apply_action(env.xp, env.state, action)
            for _ in range(env.substeps):
                mujoco.mj_step(env.model, env.data)
                contacts, rows = max(contacts, env.data.ncon), max(rows, env.data.nefc)
    assert contacts > 0 and 2 * contacts <= BATCH_KWARGS["nconmax"] and 2 * rows <= BATCH_KWARGS["njmax"]


def test_too_few_contacts_allocated_is_an_error_naming_the_key():
    from ebrl.envs.batch import MjWarpBatch

    spec = EnvSpec(id="PandaPickCube-v0", backend="mjwarp", kwargs={"device": "cpu", "nconmax": 1})
    batch = MjWarpBatch(spec, [0])
    batch.reset(np.arange(1), np.zeros(1, np.int64))
    with pytest.raises(EnvError, match="env.kwargs.nconmax"):
        batch.step(torch.zeros((1, 4)), torch.ones(1, dtype=torch.bool))


def test_preflight_and_config_say_what_is_wrong():
    preflight(SPEC)
    info = describe(EnvSpec(id="PandaPickCube-v0", backend="mjwarp"))
    assert info.obs_shape == (PandaPickCube.obs_size,) and info.action_dim == 4
    for kwargs, match in (({"device": "tpu"}, "env.kwargs.device"), ({"nconmax": 0}, "env.kwargs.nconmax"),
                          ({"colour": "red"}, "unknown env.kwargs 'colour'"), ({"model": "huge"}, "model")):
        with pytest.raises(EnvError, match=match):
            preflight(EnvSpec(id="PandaPickCube-v0", backend="mjwarp", kwargs=kwargs))
    with pytest.raises(EnvError, match="PandaPickCube-v0"):
        preflight(EnvSpec(id="PickCube", backend="mjwarp"))
    with pytest.raises(EnvError, match="MjTask subclass"):
        task_class("ebrl.envs.tasks.pick_cube:panda_pick_cube_mjcf")
    if not torch.cuda.is_available():
        with pytest.raises(EnvError, match="torch sees no CUDA device"):
            preflight(EnvSpec(id="PandaPickCube-v0", backend="mjwarp", kwargs={"device": "cuda"}))
    cfg = load(str(ROOT / "configs/mjwarp_pickcube.toml"))
    assert vectorized(cfg) and cfg.sim.groups * cfg.sim.envs_per_group >= 1024
    with pytest.raises(ConfigError, match="sim.vectorized = false"):
        load(str(ROOT / "configs/mjwarp_pickcube.toml"), ["sim.vectorized=false"])


@pytest.mark.slow  # 40-120 s: the fast suite keeps to its 10 minutes on 2 cores
def test_up_trains_the_mjwarp_config_on_the_cpu_and_stops_cleanly(tmp_path):
    """A new user's `ebrl up configs/mjwarp_pickcube.toml` on a machine without a GPU, made small: 2 groups of 4
    worlds on Warp's CPU device, 3 updates; it ends by itself, with every service stopped cleanly."""
    with up(tmp_path, "configs/mjwarp_pickcube.toml", "sim.envs_per_group=4", "train.batch_size=32",
            "run.iterations=3", 'viz.rerun="off"', name="mjwarp_cpu") as run:
        code = run.wait(400)
        summary = json.loads((run.run_dir / "summary.json").read_text())
    assert code == 0, run.output
    assert summary["iterations"] >= 3 and summary["env_steps"] > 0, summary
    # the policy the run wrote evaluates on the task's CPU MuJoCo version, as `ebrl eval` does for any run
    done = subprocess.run([sys.executable, "-m", "ebrl.cli", "eval", str(run.run_dir), "--episodes", "2",
                           "--out", str(tmp_path / "eval.json")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert json.loads((tmp_path / "eval.json").read_text())["episodes"] == 2


@pytest.mark.slow
def test_the_cpu_version_learns_to_90_percent_success(tmp_path):
    """PandaPickCube is learnable as designed: `ebrl up configs/pickcube_cpu.toml` reaches its run.target_success
    of 90 % (last 20 episodes). Measured here: 96-157 s on 2 cores (BENCHMARKS.md); allowed: 10 minutes."""
    with up(tmp_path, "configs/pickcube_cpu.toml", 'viz.rerun="off"', name="pickcube_learn") as run:
        code = run.wait(900)
    assert code == 0, run.output
    reached = json.loads((run.run_dir / "summary.json").read_text())["target_reached"]
    assert reached is not None and reached["success_rate"] >= 0.9 and reached["wall_s"] < 600, run.output


# --- on a GPU (benchmarks/gpu/check.sh mjwarp_tests runs these on the lent GPU machine)

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (benchmarks/gpu/check.sh "
                                "mjwarp_tests runs it on the lent GPU machine)")


@pytest.mark.gpu
@needs_cuda
def test_the_warp_batch_on_the_gpu_agrees_with_cpu_mujoco_and_its_graphs_with_eager_steps():
    """The same comparison as on Warp's CPU device, on the GPU with an env step's physics as one CUDA graph; and a
    batch stepped eagerly lands where the graph does."""
    from ebrl.envs.batch import MjWarpBatch

    graphed = MjWarpBatch(EnvSpec(id="PandaPickCube-v0", backend="mjwarp", kwargs={"device": "cuda"}), SEEDS)
    eager = MjWarpBatch(EnvSpec(id="PandaPickCube-v0", backend="mjwarp",
                                kwargs={"device": "cuda", "cuda_graph": False}), SEEDS)
    assert graphed.graphed and not eager.graphed and graphed.device.type == "cuda"
    test_the_warp_batch_agrees_with_cpu_mujoco_on_the_same_actions(graphed)
    steps_alike(graphed, eager, atol=1e-4)


@pytest.mark.gpu
@needs_cuda
def test_a_gpu_group_of_1024_worlds_steps_chunks_with_partial_resets():
    from ebrl.envs.batch import BatchRunner, MjWarpBatch

    spec = EnvSpec(id="PandaPickCube-v0", backend="mjwarp", max_episode_steps=10, kwargs={"device": "cuda"})
    runner = BatchRunner(MjWarpBatch(spec, list(range(1024))))
    obs = runner.reset(np.zeros(1024, np.int64))
    assert obs.shape == (1024, PandaPickCube.obs_size) and np.isfinite(obs).all()
    rng = np.random.default_rng(0)
    for _ in range(6):  # 24 steps: every world's episode ends twice
        chunk = runner.chunk(rng.uniform(-1, 1, (1024, 4, 4)).astype(np.float32))
        assert np.isfinite(chunk.next_obs).all() and np.isfinite(chunk.reward).all()
    assert (runner.episodes >= 2).all()


@pytest.mark.gpu
@needs_cuda
def test_the_gpu_config_with_no_flags_runs_simulator_generation_and_training_in_one_process(tmp_path):
    """issue 51: on a GPU host `ebrl up configs/mjwarp_pickcube.toml` shares one process among sim, gen and train
    (run.processes = "auto"), its groups stepping on that process's thread: the decision said and kept, one
    process for the three, and the run trains (its CUDA graphs captured while nothing else of the process used
    the GPU)."""
    import psutil

    with up(tmp_path, "configs/mjwarp_pickcube.toml", "run.iterations=4", 'viz.rerun="off"', name="shared-gpu") as run:
        run.wait_for_line("all services live", 600)
        shared = [c for c in psutil.Process(run.proc.pid).children() if "ebrl.process" in c.cmdline()]
        assert len(shared) == 1 and shared[0].children() == []  # the groups step on its thread
        code = run.wait(600)
    assert code == 0, run.output[-4000:]
    assert "auto: run.processes = [['sim', 'gen', 'train']]" in run.output
    assert load(str(run.run_dir / "config.toml"), []).run.processes == [["sim", "gen", "train"]]
    assert json.loads((run.run_dir / "summary.json").read_text())["iterations"] == 4
