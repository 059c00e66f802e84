"""What each ``run.mode`` turns on (shared/DESIGN.md section 4), as data: a leaf that the config's checks and the
schedule (``ebrl.sched.modes.resolve``, which turns a mode and the ablation switches into what every service
follows) both read. An explicit ``sim.stepping``, ``sim.core_rebinding``, ``sim.group_pipeline``,
``sim.lazy_render`` or ``train.overlap`` overrides the mode's choice (the ablations).

``lazy_render``: rendering only the observations a policy reads is EBRL's; the baselines render every step's, as
RLinf's LIBERO env does (``chunk_step`` steps its vector env once per action, each step rendering the cameras)."""

from __future__ import annotations

from typing import Any

PRESETS: dict[str, dict[str, Any]] = {
    "ebrl": dict(group_pipeline=True, stepping="async", core_rebinding="auto", overlap=True, disjoint=False,
                 lazy_render=True),
    "colocated": dict(group_pipeline=False, stepping="batch", core_rebinding=False, overlap=False, disjoint=False,
                      lazy_render=False),
    "hybrid": dict(group_pipeline=True, stepping="batch", core_rebinding=False, overlap=False, disjoint=False,
                   lazy_render=False),
    "async": dict(group_pipeline=False, stepping="batch", core_rebinding=False, overlap=True, disjoint=True,
                  lazy_render=False),
}
