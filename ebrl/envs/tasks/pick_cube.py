"""PandaPickCube: a Franka Panda picks a 4 cm cube off a table and holds it at a target in the air.

The robot is robosuite's Panda (robosuite 1.5.1, MIT licence, installed with EBRL): its kinematics, joint limits
and damping, and the explicit inertia of every body, with its parallel-jaw gripper. Two variants of the model:

* ``model = "simple"`` (the default, and what MuJoCo Warp steps): no meshes at all (the arm is drawn as capsules,
  which touch nothing). Only the gripper collides:
  the hand as one box (the oriented bounding box of robosuite's hand collision mesh) and the two finger pads
  (robosuite's own pad boxes), as MuJoCo Playground's Panda (Menagerie's panda_mjx) collides only through its
  hand capsule and finger pads. The arm's links collide with nothing.
* ``model = "full"``: robosuite's visual meshes on every link and its collision meshes (links, hand, fingers) as
  well. For CPU MuJoCo and pictures; tests/test_mjwarp.py checks that the simple model's rollouts under the same
  actions match it.

The hand follows a mocap target through a weld (Cartesian control at a fixed downward orientation, as Gymnasium
Robotics' Fetch tasks and robosuite's OSC controller give it), the arm's bodies gravity-compensated. An action
is 4 numbers in [-1, 1]: the target's move in x, y, z (up to ``MOVE`` metres per step, kept inside the
workspace) and the gripper's opening (-1 closed, 1 open).

Reward, in the spirit of MuJoCo Playground's and ManiSkill's PickCube (reach, grasp, lift to the target), each
step: ``reach = 1 - tanh(5 d_reach)`` + ``grasped`` + ``grasped * (1 - tanh(5 d_goal))``, all over 3 (so in
[0, 1]); a step in success is worth 1, the most a step gives. ``d_reach``: grip point to cube centre; ``d_goal``:
cube centre to target; ``grasped``: the grip point within 3 cm of the cube's centre with the fingers closed on it
(their travel between 2 and 4.5 cm: neither open nor shut on nothing). Success: the cube's centre within 5 cm of
the target, held (a cube flicked through the target does not count); an episode succeeds if it was ever there.
A success does not end the episode (100 steps): holding the cube at the target is what pays. (Ending it there
would make a near-success worth more than a success: 0.9 a step on and on against one step of 1; a first
version that did stalled at 6-9 % success from its 2nd to its 7th minute on 2 cores.) The cube falling off the
table ends an episode as a failure.
"""

from __future__ import annotations

import importlib.util
import os
from typing import Any

import numpy as np
from array_api_compat import device

from ebrl.envs.mjtask import MjInit, MjState, MjTask
from ebrl.envs.spec import EnvError

# the arm's rest pose (robosuite's Panda init_qpos) and the gripper open
HOME_QPOS = (0.0, np.pi / 16, 0.0, -np.pi / 2 - np.pi / 3, 0.0, np.pi - 0.2, np.pi / 4)
FINGER_OPEN = 0.04  # each finger's travel (robosuite's joint range)
CUBE_HALF = 0.02
MOVE = 0.02  # metres the hand target moves per step at |action| = 1
# where the hand target may go (the hand frame; the grip point is GRIP_BELOW_HAND below it)
WORKSPACE_LOW = (0.25, -0.35, 0.105)
WORKSPACE_HIGH = (0.75, 0.35, 0.45)
CUBE_CENTRE = (0.45, 0.0)
CUBE_RANGE = (0.1, 0.15)  # +- x, y of the cube's start
TARGET_RANGE = (0.1, 0.15)  # +- x, y of the target around CUBE_CENTRE
TARGET_HEIGHT = (0.1, 0.25)  # the target's height above the table
SUCCESS_DISTANCE = 0.05
GRASP_DISTANCE = 0.03  # a cube held by its edge has its centre up to 2.8 cm (half a diagonal) from the pads
# the fingers' travel summed (q1 - q2) while they hold the 4 cm cube: about 3.3 cm, the pads sinking into it under
# the actuators' 20 N; shut on nothing it is 0, open 8 cm
GRASP_GAP = (0.02, 0.045)
HAND_HOME = (0.445, 0.0, 0.195)  # the hand's position in HOME_QPOS (forward kinematics, checked by a test)
HAND_DOWN = (0.0, 1.0, 0.0, 0.0)  # the hand pointing down (quaternion w, x, y, z)


def robosuite_assets() -> str:
    """robosuite's model assets folder, found without importing robosuite (whose import is slow and noisy)."""
    spec = importlib.util.find_spec("robosuite")
    if spec is None or not spec.submodule_search_locations:
        raise EnvError("PandaPickCube builds its Panda from robosuite's assets: pip install robosuite==1.5.1")
    return os.path.join(list(spec.submodule_search_locations)[0], "models", "assets")


# the arm: (body, parent offset, parent quat, inertial pos, mass, diag inertia, joint range, damping) from
# robosuite/models/assets/robots/panda/robot.xml
LINKS = (
    ("link1", "0 0 0.333", "1 0 0 0", "0 0 -0.07", 3, "0.3 0.3 0.3", "-2.8973 2.8973", 0.1),
    ("link2", "0 0 0", "0.707107 -0.707107 0 0", "0 -0.1 0", 3, "0.3 0.3 0.3", "-1.7628 1.7628", 0.1),
    ("link3", "0 -0.316 0", "0.707107 0.707107 0 0", "0.04 0 -0.05", 2, "0.2 0.2 0.2", "-2.8973 2.8973", 0.1),
    ("link4", "0.0825 0 0", "0.707107 0.707107 0 0", "-0.04 0.05 0", 2, "0.2 0.2 0.2", "-3.0718 -0.0698", 0.1),
    ("link5", "-0.0825 0.384 0", "0.707107 -0.707107 0 0", "0 0 -0.15", 2, "0.2 0.2 0.2", "-2.8973 2.8973", 0.1),
    ("link6", "0 0 0", "0.707107 0.707107 0 0", "0.06 0 0", 1.5, "0.1 0.1 0.1", "-0.0175 3.7525", 0.01),
    ("link7", "0.088 0 0", "0.707107 0.707107 0 0", "0 0 0.08", 0.5, "0.05 0.05 0.05", "-2.8973 2.8973", 0.01),
)
VISUAL_MESHES = {"link0": 12, "link1": 1, "link2": 1, "link3": 4, "link4": 4, "link5": 3, "link6": 17, "link7": 8}


# the simple model's look: a capsule from each link's origin to the next one's (visual only, group 1: no contact,
# no mass, since every body's inertia is explicit), so that videos show an arm
SIMPLE_LOOK = {"link0": "0 0 0 0 0 0.333", "link2": "0 0 0 0 -0.316 0", "link3": "0 0 0 0.0825 0 0",
               "link4": "0 0 0 -0.0825 0.384 0", "link6": "0 0 0 0.088 0 0", "link7": "0 0 0 0 0 0.1065"}


def _visuals(link: str, full: bool) -> str:
    if not full:
        fromto = SIMPLE_LOOK.get(link)
        shape = f'type="capsule" fromto="{fromto}"' if fromto else 'type="sphere"'
        return f'<geom class="visual" {shape} size="0.055"/>'
    n = VISUAL_MESHES[link]
    names = [f"{link}_vis"] if n == 1 else [f"{link}_vis_{i}" for i in range(n)]
    geoms = "".join(f'<geom class="visual" mesh="{name}"/>' for name in names)
    return geoms + f'<geom class="collision_mesh" mesh="{link}"/>'


def _mesh_assets(root: str) -> str:
    panda = f"{root}/robots/panda"
    lines = [f'<mesh name="link{i}" file="{panda}/meshes/link{i}.stl"/>' for i in range(8)]
    for link, n in VISUAL_MESHES.items():
        names = [f"{link}_vis"] if n == 1 else [f"{link}_vis_{i}" for i in range(n)]
        lines += [f'<mesh name="{name}" file="{panda}/obj_meshes/{link}_vis/{name}.obj"/>' for name in names]
    grip = f"{root}/grippers/meshes/panda_gripper"
    lines += [f'<mesh name="hand" file="{grip}/hand.stl"/>', f'<mesh name="hand_vis" file="{grip}/hand_vis.stl"/>',
              f'<mesh name="finger" file="{grip}/finger.stl"/>',
              f'<mesh name="finger_vis" file="{grip}/finger_vis.stl"/>']
    return "\n    ".join(lines)


def _arm(full: bool, gripper: str) -> str:
    """Links 1 to 7, each body inside its parent's (robot.xml's chain), with ``gripper`` inside link 7."""
    arm = gripper
    for name, pos, quat, ipos, mass, inertia, jrange, damping in reversed(LINKS):
        joint = f'<joint name="joint{name[-1]}" range="{jrange}" damping="{damping}"/>'
        arm = (f'<body name="{name}" pos="{pos}" quat="{quat}" gravcomp="1">'
               f'<inertial pos="{ipos}" mass="{mass}" diaginertia="{inertia}"/>{joint}{_visuals(name, full)}'
               f'{arm}</body>')
    return arm


def _hand_geoms(full: bool) -> tuple[str, str]:
    """The hand's geoms, and each finger's (``QUAT`` where the finger's orientation goes): robosuite's meshes in
    the full model; in the simple one the hand's collision mesh as its oriented bounding box (MuJoCo's own fit of
    the mesh, rounded) and no finger geoms but the pads."""
    if full:
        hand = ('<geom class="visual" mesh="hand_vis" quat="0.707107 0 0 0.707107"/>'
                '<geom class="collision_mesh" mesh="hand" quat="0.707107 0 0 0.707107"/>')
        finger = ('<geom class="visual" mesh="finger_vis" QUAT/>'
                  '<geom class="finger_mesh" mesh="finger" QUAT/>')
        return hand, finger
    hand = ('<geom name="hand_box" type="box" size="0.0316 0.0487 0.1039" pos="0.0006 0 0.0239" '
            'quat="0.4935 0.5066 0.5062 0.4936" rgba="0.9 0.9 0.9 1"/>')
    return hand, ""


def _fingers(finger: str) -> str:
    """The two sliding fingers, mirror images of each other, each with its pad (the box that grips the cube) on a
    tip body; ``finger``: their geoms (:func:`_hand_geoms`)."""
    fingers = ""
    for side, sign in (("1", 1), ("2", -1)):
        joint_range = "0 0.04" if sign > 0 else "-0.04 0"
        quat = '' if sign > 0 else 'quat="0 0 0 1"'
        fingers += (
            f'<body name="finger{side}" pos="0 0 0.0524" quat="0.707107 0 0 0.707107">'
            f'<inertial pos="0 0 0.05" mass="0.1" diaginertia="0.01 0.01 0.005"/>'
            f'<joint name="finger_joint{side}" type="slide" axis="0 1 0" range="{joint_range}" damping="100" '
            f'armature="1.0" frictionloss="1.0"/>{finger.replace("QUAT", quat)}'
            f'<body name="finger{side}_tip" pos="0 {sign * 0.0085} 0.056">'
            f'<inertial pos="0 0 0" mass="0.01" diaginertia="0.01 0.01 0.01"/>'
            f'<geom name="finger{side}_pad" class="pad" pos="0 {-sign * 0.005} -0.015"/></body></body>')
    return fingers


def _gripper(full: bool) -> str:
    """The hand on link 7's flange, with the grip point (site ``grip``) and the two fingers."""
    hand, finger = _hand_geoms(full)
    return ('<body name="hand" pos="0 0 0.1065" quat="0.924 0 0 -0.383" gravcomp="1">'
            '<inertial pos="0 0 0" mass="0.5" diaginertia="0.05 0.05 0.05"/>'
            '<body name="gripper" quat="0.707107 0 0 -0.707107" gravcomp="1">'
            '<inertial pos="0 0 0.17" quat="0.707107 0.707107 0 0" mass="0.3" diaginertia="0.09 0.07 0.05"/>'
            f'{hand}<site name="grip" pos="0 0 0.097" size="0.01" rgba="1 0 0 0.5" group="2"/>{_fingers(finger)}'
            '</body></body>')


# the compiler, the physics options and the geoms' defaults (which of them collide with what), in both models
_SETTINGS = """  <compiler angle="radian" autolimits="true"/>
  <option timestep="0.005" integrator="implicitfast" cone="pyramidal">
    <!-- MuJoCo's own box-box collider on both engines: MuJoCo Warp's native CCD gives one contact per finger pad
         on the cube (the pads then sink 1 cm into it under the grip), the dedicated collider four, as CPU MuJoCo -->
    <flag nativeccd="disable"/>
  </option>
  <default>
    <geom contype="0" conaffinity="0"/>
    <default class="visual"><geom type="mesh" group="1" rgba="0.9 0.9 0.9 1"/></default>
    <default class="collision_mesh"><geom type="mesh" group="3" contype="1" conaffinity="1"/></default>
    <default class="finger_mesh"><geom type="mesh" group="3" contype="0" conaffinity="1"/></default>
    <default class="pad"><geom type="box" size="0.008 0.004 0.008" contype="1" conaffinity="1" friction="2 0.05 0.0001"
      solref="0.01 1" rgba="0.3 0.3 0.3 1"/></default>
  </default>"""

# the hand welded to its mocap target (Cartesian control) and the fingers' position actuators
_CONTROL = """  <equality>
    <weld body1="hand_target" body2="hand" relpose="0 0 0 1 0 0 0" solref="0.02 1"/>
  </equality>
  <actuator>
    <position name="finger1" joint="finger_joint1" ctrlrange="0 0.04" kp="1000" forcerange="-20 20"/>
    <position name="finger2" joint="finger_joint2" ctrlrange="-0.04 0" kp="1000" forcerange="-20 20"/>
  </actuator>"""


def _task_bodies() -> str:
    """The cube on the table, the green target it is to be held at, and the hand's mocap target at its home."""
    hx, hy, hz = HAND_HOME
    return f"""<body name="cube" pos="{CUBE_CENTRE[0]} {CUBE_CENTRE[1]} {CUBE_HALF}">
      <freejoint name="cube"/>
      <geom name="cube" type="box" size="{CUBE_HALF} {CUBE_HALF} {CUBE_HALF}" mass="0.064" contype="1" conaffinity="1"
        friction="1 0.005 0.0001" solref="0.01 1" rgba="0.8 0.1 0.1 1"/>
    </body>
    <body name="target" mocap="true" pos="{CUBE_CENTRE[0]} {CUBE_CENTRE[1]} 0.2">
      <geom type="sphere" size="0.01" rgba="0.1 0.8 0.1 0.6" group="2"/>
    </body>
    <body name="hand_target" mocap="true" pos="{hx} {hy} {hz}" quat="0 1 0 0"/>"""


def panda_pick_cube_mjcf(full: bool = False) -> str:
    """The task's MJCF: ``full`` with robosuite's meshes (visual and collision), else the simple model."""
    arm = _arm(full, _gripper(full))
    assets = _mesh_assets(robosuite_assets()) if full else ""
    return f"""<mujoco model="panda_pick_cube">
{_SETTINGS}
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.2 0.3 0.4" rgb2="0.1 0.2 0.3" width="256" height="256"/>
    <material name="grid" texture="grid" texrepeat="4 4"/>
    {assets}
  </asset>
  <visual><global offwidth="640" offheight="640"/></visual>
  <worldbody>
    <light pos="0.5 0 1.5" dir="0 0 -1" directional="true"/>
    <camera name="front" pos="1.45 0.55 0.85" xyaxes="-0.35 0.94 0 -0.45 -0.17 0.88" fovy="55"/>
    <geom name="floor" type="plane" pos="0 0 -0.8" size="2 2 0.1" material="grid"/>
    <geom name="table" type="box" pos="0.4 0 -0.02" size="0.5 0.6 0.02" contype="1" conaffinity="1"
      rgba="0.6 0.5 0.4 1"/>
    <body name="link0" pos="0 0 0">
      <inertial pos="0 0 0.05" mass="4" diaginertia="0.4 0.4 0.4"/>
      {_visuals("link0", full)}
      {arm}
    </body>
    {_task_bodies()}
  </worldbody>
{_CONTROL}
</mujoco>"""


class PandaPickCube(MjTask):
    """The task (module doc). ``model``: "simple" (default) or "full"."""

    ctrl_dt = 0.02  # 4 physics steps of 5 ms
    max_episode_steps = 100  # 2 s
    action_size = 4
    obs_size = 40
    instruction = "pick up the red cube and hold it at the green target"
    reward_range = (0.0, 1.0)  # evaluate's reward: a mean of three terms in [0, 1], 1 on success

    def __init__(self, model: str = "simple", **kwargs: Any):
        if model not in ("simple", "full"):
            raise EnvError(f"PandaPickCube model = {model!r}: expected \"simple\" or \"full\"")
        super().__init__(**kwargs)
        self.full = model == "full"

    def mjcf(self) -> tuple[str, dict[str, bytes]]:
        return panda_pick_cube_mjcf(self.full), {}

    def bind(self, model: Any) -> None:
        import mujoco

        def ident(kind: Any, name: str) -> int:
            return mujoco.mj_name2id(model, kind, name)

        joint = mujoco.mjtObj.mjOBJ_JOINT
        self.arm_qpos = [int(model.jnt_qposadr[ident(joint, f"joint{i}")]) for i in range(1, 8)]
        self.arm_dof = [int(model.jnt_dofadr[ident(joint, f"joint{i}")]) for i in range(1, 8)]
        self.finger_qpos = [int(model.jnt_qposadr[ident(joint, f"finger_joint{i}")]) for i in (1, 2)]
        self.finger_dof = [int(model.jnt_dofadr[ident(joint, f"finger_joint{i}")]) for i in (1, 2)]
        cube_joint = ident(joint, "cube")
        self.cube_qpos = int(model.jnt_qposadr[cube_joint])
        self.grip_site = ident(mujoco.mjtObj.mjOBJ_SITE, "grip")
        self.target_mocap = int(model.body_mocapid[ident(mujoco.mjtObj.mjOBJ_BODY, "target")])
        self.hand_mocap = int(model.body_mocapid[ident(mujoco.mjtObj.mjOBJ_BODY, "hand_target")])
        self.nq, self.nv = model.nq, model.nv

    def task_fields(self) -> dict[str, tuple[int, ...]]:
        return {"target": (3,)}

    def initial_state(self, rng: np.random.Generator) -> MjInit:
        _ = self.model  # built, and bound (the indices below), on first use
        qpos = np.zeros(self.nq)
        qpos[self.arm_qpos] = HOME_QPOS
        qpos[self.finger_qpos] = (FINGER_OPEN, -FINGER_OPEN)
        cube_xy = np.asarray(CUBE_CENTRE) + rng.uniform(-1.0, 1.0, 2) * CUBE_RANGE
        qpos[self.cube_qpos:self.cube_qpos + 7] = (*cube_xy, CUBE_HALF, 1.0, 0.0, 0.0, 0.0)
        target = np.array([*(np.asarray(CUBE_CENTRE) + rng.uniform(-1.0, 1.0, 2) * TARGET_RANGE),
                           rng.uniform(*TARGET_HEIGHT)])
        mocap_pos = np.zeros((2, 3))
        mocap_quat = np.zeros((2, 4))
        mocap_pos[self.hand_mocap], mocap_quat[self.hand_mocap] = HAND_HOME, HAND_DOWN
        mocap_pos[self.target_mocap], mocap_quat[self.target_mocap] = target, (1.0, 0.0, 0.0, 0.0)
        ctrl = np.array([FINGER_OPEN, -FINGER_OPEN])
        return MjInit(qpos, np.zeros(self.nv), mocap_pos, mocap_quat, ctrl, {"target": target.astype(np.float32)})

    def apply_action(self, xp: Any, state: MjState, action: Any) -> None:
        hand = state.mocap_pos[:, self.hand_mocap, :]
        low = xp.asarray(WORKSPACE_LOW, dtype=hand.dtype, device=device(hand))
        high = xp.asarray(WORKSPACE_HIGH, dtype=hand.dtype, device=device(hand))
        move = xp.astype(action[:, :3], hand.dtype) * MOVE
        state.mocap_pos[:, self.hand_mocap, :] = xp.minimum(xp.maximum(hand + move, low), high)
        opening = (xp.astype(action[:, 3], state.ctrl.dtype) + 1.0) * (FINGER_OPEN / 2)
        state.ctrl[:, 0] = opening
        state.ctrl[:, 1] = -opening

    def _parts(self, xp: Any, state: MjState) -> tuple[Any, Any, Any, Any]:
        grip = state.site_xpos[:, self.grip_site, :]
        cube = state.qpos[:, self.cube_qpos:self.cube_qpos + 3]
        gap = state.qpos[:, self.finger_qpos[0]] - state.qpos[:, self.finger_qpos[1]]
        target = xp.astype(state.task["target"], cube.dtype)
        return grip, cube, gap, target

    def observe(self, xp: Any, state: MjState) -> Any:
        grip, cube, _, target = self._parts(xp, state)
        q = state.qpos
        parts = [grip, q[:, self.finger_qpos[0]:self.finger_qpos[0] + 2], state.qvel[:, self.finger_dof[0]:
                 self.finger_dof[0] + 2], cube, q[:, self.cube_qpos + 3:self.cube_qpos + 7], cube - grip, target,
                 target - cube, q[:, self.arm_qpos[0]:self.arm_qpos[0] + 7],
                 state.qvel[:, self.arm_dof[0]:self.arm_dof[0] + 7], state.mocap_pos[:, self.hand_mocap, :]]
        return xp.astype(xp.concat([xp.astype(p, cube.dtype) for p in parts], axis=1), xp.float32)

    def evaluate(self, xp: Any, state: MjState) -> tuple[Any, Any, Any]:
        grip, cube, gap, target = self._parts(xp, state)
        d_reach = xp.linalg.vector_norm(cube - grip, axis=-1)
        d_goal = xp.linalg.vector_norm(target - cube, axis=-1)
        grasped = (d_reach < GRASP_DISTANCE) & (gap > GRASP_GAP[0]) & (gap < GRASP_GAP[1])
        held = xp.astype(grasped, cube.dtype)
        reward = ((1.0 - xp.tanh(5.0 * d_reach)) + held + held * (1.0 - xp.tanh(5.0 * d_goal))) / 3.0
        success = (d_goal < SUCCESS_DISTANCE) & grasped  # held there: a cube flicked through the target is no success
        reward = xp.where(success, xp.ones_like(reward), reward)
        fell = cube[:, 2] < -0.05
        return reward, success, fell
