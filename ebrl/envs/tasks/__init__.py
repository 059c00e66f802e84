"""The MuJoCo tasks EBRL ships (ebrl/envs/mjtask.py), registered with gymnasium on import, so each also runs on
CPU MuJoCo as ``env.backend = "gymnasium"``, ``env.id = "ebrl.envs.tasks:PandaPickCube-v0"``; under
``env.backend = "mjwarp"`` the same task is ``env.id = "PandaPickCube-v0"``."""

import gymnasium

from ebrl.envs.mjtask import TASKS, task_class

for _name in TASKS:
    if _name not in gymnasium.registry:
        gymnasium.register(_name, entry_point="ebrl.envs.mjtask:make_gym_env", kwargs={"task": _name},
                           max_episode_steps=task_class(_name).max_episode_steps)
