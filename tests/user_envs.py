"""A user's own environment package, registered on import (used as env.id = "user_envs:ShortPendulum-v0")."""

import gymnasium

gymnasium.register(
    "ShortPendulum-v0",
    entry_point="gymnasium.envs.mujoco.inverted_pendulum_v5:InvertedPendulumEnv",
    max_episode_steps=10,
)


class SeedSuccess(gymnasium.Env):
    """Five steps of reward 1; ``info["success"]`` at the last step when the episode's reset seed is even (so an
    evaluation over consecutive seeds succeeds in exactly half of its episodes). Renders a grey frame."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, render_mode=None):
        import numpy as np

        self.np, self.render_mode = np, render_mode
        self.observation_space = gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.t, self.even = 0, False

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.even = 0, seed is not None and seed % 2 == 0
        return self.np.zeros(4, self.np.float32), {}

    def step(self, action):
        self.t += 1
        done = self.t >= 5
        return self.np.full(4, self.t / 5, self.np.float32), 1.0, False, done, {"success": done and self.even}

    def render(self):
        return self.np.full((32, 48, 3), 40 * self.t, self.np.uint8)


gymnasium.register("SeedSuccess-v0", entry_point=SeedSuccess)


class ThreadedStep(gymnasium.Env):
    """A simulator that steps on two threads, as multi-threaded physics does: a helper thread, started with the
    env, hashes one buffer while the stepping thread hashes another (hashlib releases the GIL), and the step
    returns when both are done. 20-step episodes."""

    def __init__(self, work_bytes: int = 1 << 18):
        import hashlib
        import queue
        import threading

        import numpy as np

        self.np, self.hashlib = np, hashlib
        self.observation_space = gymnasium.spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.buffers = (bytes(work_bytes), bytes(range(256)) * (work_bytes // 256))
        self.todo, self.done = queue.Queue(), queue.Queue()
        self.helper = threading.Thread(target=self._help, name="physics-helper", daemon=True)
        self.helper.start()
        self.t = 0

    def _help(self):
        while (job := self.todo.get()) is not None:
            self.done.put(self.hashlib.sha256(job).digest())

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self.np.zeros(3, self.np.float32), {}

    def step(self, action):
        self.todo.put(self.buffers[1])
        self.hashlib.sha256(self.buffers[0]).digest()
        self.done.get()
        self.t += 1
        return self.np.full(3, self.t / 20, self.np.float32), 1.0, False, self.t >= 20, {}

    def close(self):
        self.todo.put(None)


gymnasium.register("ThreadedStep-v0", entry_point=ThreadedStep)


from ebrl.envs.mjtask import MjInit, MjTask  # noqa: E402  (a user's own MuJoCo task, env.backend = "mjwarp")


class SlidingBlock(MjTask):
    """The smallest MuJoCo task: a block on a rail, pushed by a motor, rewarded for staying near 0 (named
    "user_envs:SlidingBlock"). ``explode_after``: world 0's control turns to NaN after that many steps, as a
    diverging simulation's state would."""

    ctrl_dt = 0.02
    max_episode_steps = 50
    action_size = 1
    obs_size = 2

    def __init__(self, explode_after: int = 0, **kwargs):
        super().__init__(**kwargs)
        self.explode_after = explode_after

    def mjcf(self):
        return ('<mujoco><option timestep="0.01"/><worldbody><body><joint name="x" type="slide" axis="1 0 0"/>'
                '<geom type="box" size=".05 .05 .05" mass="1"/></body></worldbody>'
                '<actuator><motor joint="x"/></actuator></mujoco>', {})

    def task_fields(self):
        return {"t": ()}

    def initial_state(self, rng):
        import numpy as np

        return MjInit(qpos=np.array([rng.uniform(-0.1, 0.1)]), qvel=np.zeros(1))

    def apply_action(self, xp, state, action):
        state.ctrl[:, 0] = action[:, 0]
        state.task["t"] += 1
        if self.explode_after and float(state.task["t"][0]) > self.explode_after:
            state.ctrl[0, 0] = float("nan")

    def observe(self, xp, state):
        return xp.astype(xp.concat([state.qpos, state.qvel], axis=1), xp.float32)

    def evaluate(self, xp, state):
        x = state.qpos[:, 0]
        return -xp.abs(x), xp.abs(x) < 0.01, xp.zeros_like(x, dtype=xp.bool)


class GoalImage(gymnasium.Env):
    """A user's own goal-conditioned env with a nested Dict observation, as EBRL reads it with no wrapper
    ("user_envs:GoalImage-v0"): ``{"camera": {"rgb": 16x16x3 uint8}, "robot": {"position": (2,)}, "goal": (2,),
    "task": Text}``. A point moves by the action (clipped to [-1, 1]^2); reward: minus its distance to the goal,
    drawn in the image as a bright pixel (the point as a grey one). 20-step episodes; ``info["is_success"]`` within
    0.1 of the goal (gymnasium-robotics' key)."""

    SIZE = 16

    def __init__(self):
        import numpy as np

        spaces = gymnasium.spaces
        self.np = np
        self.observation_space = spaces.Dict({
            "camera": spaces.Dict({"rgb": spaces.Box(0, 255, (self.SIZE, self.SIZE, 3), np.uint8)}),
            "robot": spaces.Dict({"position": spaces.Box(-1.0, 1.0, (2,), np.float32)}),
            "goal": spaces.Box(-1.0, 1.0, (2,), np.float32),
            "task": spaces.Text(64, charset="abcdefghijklmnopqrstuvwxyz "),
        })
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.t = 0

    def _pixel(self, xy):
        return tuple(int(round((v + 1) / 2 * (self.SIZE - 1))) for v in xy)

    def _obs(self):
        np = self.np
        image = np.zeros((self.SIZE, self.SIZE, 3), np.uint8)
        image[self._pixel(self.goal)] = 255
        image[self._pixel(self.position)] = (128, 128, 128)
        return {"camera": {"rgb": image}, "robot": {"position": self.position.copy()}, "goal": self.goal.copy(),
                "task": "reach the goal"}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        self.position = self.np_random.uniform(-1, 1, 2).astype(self.np.float32)
        self.goal = self.np_random.uniform(-1, 1, 2).astype(self.np.float32)
        return self._obs(), {}

    def step(self, action):
        np = self.np
        self.position = np.clip(self.position + 0.2 * np.clip(np.asarray(action, np.float32), -1, 1), -1, 1)
        self.t += 1
        distance = float(np.linalg.norm(self.position - self.goal))
        return self._obs(), -distance, False, self.t >= 20, {"is_success": distance < 0.1}


gymnasium.register("GoalImage-v0", entry_point=GoalImage)


class CountsRenders(gymnasium.Env):
    """A camera env that renders on demand, as robosuite's and LIBERO's do (``skip_observation``, ``observe()``):
    its observation is how many times it has rendered, so a chunk's last observation tells how many of its
    steps rendered."""

    def __init__(self):
        import numpy as np

        self.np = np
        self.observation_space = gymnasium.spaces.Box(0.0, 1e9, (1,), np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.renders, self.skip_observation, self.t = 0, False, 0

    def observe(self):
        self.renders += 1
        return self.np.array([self.renders], self.np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self.observe(), {}

    def step(self, action):
        self.t += 1
        obs = self.np.array([self.renders], self.np.float32) if self.skip_observation else self.observe()
        return obs, 0.0, False, self.t >= 1000, {}


gymnasium.register("CountsRenders-v0", entry_point=CountsRenders)


class DictPendulum(gymnasium.Env):
    """Pendulum-v1 with a user's Dict observation of two named parts (no images): what EBRL flattens by its
    layout for any algorithm, SAC's replay included."""

    def __init__(self, render_mode=None):
        import numpy as np

        spaces = gymnasium.spaces
        self.inner = gymnasium.make("Pendulum-v1").unwrapped
        self.observation_space = spaces.Dict({"angle": spaces.Box(-1.0, 1.0, (2,), np.float32),
                                              "velocity": spaces.Box(-8.0, 8.0, (1,), np.float32)})
        self.action_space = self.inner.action_space

    @staticmethod
    def split(obs):
        return {"angle": obs[:2].astype("float32"), "velocity": obs[2:].astype("float32")}

    def reset(self, *, seed=None, options=None):
        obs, info = self.inner.reset(seed=seed)
        return self.split(obs), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.inner.step(action)
        return self.split(obs), reward, terminated, truncated, info


gymnasium.register("DictPendulum-v0", entry_point=DictPendulum, max_episode_steps=200)
