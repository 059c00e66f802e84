"""Offscreen rendering backend for camera observations: pick MuJoCo's ``MUJOCO_GL`` before anything imports it.

MuJoCo reads ``MUJOCO_GL`` (and PyOpenGL ``PYOPENGL_PLATFORM``) once, on
import, so a process cannot switch backend later: the choice is made before
mujoco/robosuite are imported (and before the env workers' forkserver starts,
since workers inherit its environment). Each candidate is tried by rendering a
tiny model in a short subprocess; the winner is exported to ``os.environ`` so
that child processes inherit it without trying again.
"""

from __future__ import annotations

import ctypes.util
import os
import re
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ebrl.envs.records import backend_record

PROBE_TIMEOUT_S = 30.0
# set by choose_gl to the backend it decided on: a child process trusts it instead of deciding again
CHOSEN_VAR = "EBRL_MUJOCO_GL"
_PYOPENGL_PLATFORM = {"egl": "egl", "osmesa": "osmesa", "glx": "glx"}  # glfw picks its own

_PROBE = """
import mujoco
model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='.1'/></worldbody></mujoco>")
data = mujoco.MjData(model)
mujoco.mj_forward(model, data)
with mujoco.Renderer(model, 8, 8) as renderer:
    renderer.update_scene(data)
    assert renderer.render().shape == (8, 8, 3)
"""

_chosen: str | None = None


class RenderingUnavailable(RuntimeError):
    """No offscreen OpenGL backend works in this process; the message says what was tried and how to fix it."""


def choose_gl(candidates: Sequence[str] | None = None) -> str:
    """The ``MUJOCO_GL`` backend for camera observations, decided once per process and exported to children.

    An explicit ``MUJOCO_GL`` (or ``PYOPENGL_PLATFORM``) is used as given. Otherwise each candidate
    (default: ``egl`` first where an NVIDIA GPU is present, then ``osmesa``; Mesa's software ``egl`` last
    without one) is tried in a subprocess, and the first that renders wins.
    """
    global _chosen
    if _chosen is None:
        backend = os.environ.get(CHOSEN_VAR) or _explicit_gl()
        if not backend:
            backend = _first_working(list(candidates) if candidates is not None else default_candidates())
        os.environ[CHOSEN_VAR] = os.environ["MUJOCO_GL"] = backend
        if backend in _PYOPENGL_PLATFORM:
            os.environ["PYOPENGL_PLATFORM"] = _PYOPENGL_PLATFORM[backend]
        _chosen = backend
    return _chosen


def ensure_gl_for(spec: Any) -> str | None:
    """Choose the backend now if the environment ``spec`` (an EnvSpec) renders camera observations with MuJoCo's
    GL (its record's ``gl_cameras``: robosuite's and LIBERO's); None when it renders nothing so. Call it before
    mujoco/robosuite are imported and before env workers start."""
    record = backend_record(spec.backend)
    return choose_gl() if record.gl_cameras and record.cameras(spec.kwargs) else None


def with_rendering(spec: Any) -> Any:
    """``spec`` (an EnvSpec) built so that ``env.render()`` returns RGB frames (evaluation videos): every backend
    takes ``render_mode="rgb_array"``. MuJoCo-based backends (their records' ``gl_frames``) render offscreen, so
    the GL backend is chosen now: call it before mujoco is imported in this process."""
    import dataclasses

    if backend_record(spec.backend).gl_frames:
        choose_gl()
    return dataclasses.replace(spec, kwargs={**spec.kwargs, "render_mode": "rgb_array"})


def default_candidates() -> list[str]:
    return ["egl", "osmesa"] if _has_nvidia_gpu() else ["osmesa", "egl"]


def _has_nvidia_gpu() -> bool:
    return Path("/dev/nvidia0").exists() or ctypes.util.find_library("EGL_nvidia") is not None


def _explicit_gl() -> str | None:
    value = os.environ.get("MUJOCO_GL", "").strip().lower()
    if value == "egl" and _written_by_robosuite():
        value = ""
    if value:
        return value
    platform = os.environ.get("PYOPENGL_PLATFORM", "").strip().lower()
    return platform if platform in ("egl", "osmesa") else None


def _written_by_robosuite() -> bool:
    # robosuite writes MUJOCO_GL=egl on import (macros.MUJOCO_GPU_RENDERING) unless it is osmesa or glx. It imports
    # mujoco first, which keeps the value it read: an "egl" that mujoco did not see is robosuite's, nobody's choice
    return "robosuite.utils.binding_utils" in sys.modules and getattr(_mujoco_gl_context(), "_MUJOCO_GL", "") != "egl"


# where mujoco keeps the MUJOCO_GL it read on import: MuJoCo 3.9 moved its GL context module, and the old name
# re-exports it with `import *`, which leaves the private value behind
GL_CONTEXT_MODULES = ("mujoco.rendering.classic.gl_context", "mujoco.gl_context")


def _mujoco_gl_context() -> Any:
    """mujoco's imported GL context module (None before mujoco's import)."""
    return next((sys.modules[name] for name in GL_CONTEXT_MODULES if name in sys.modules), None)


def _first_working(candidates: list[str]) -> str:
    failures = []
    for backend in candidates:
        why = _probe(backend)
        if why is None:
            return backend
        failures.append(f"  MUJOCO_GL={backend}: {why}")
    tried = "\n".join(failures) or "  (no candidates)"
    raise RenderingUnavailable(
        "camera observations need MuJoCo offscreen rendering (OpenGL), and no backend works here:\n"
        f"{tried}\n"
        "Fix: on a CPU machine install OSMesa (apt-get install libosmesa6); on an NVIDIA GPU install the driver "
        "with EGL (libEGL_nvidia); or set MUJOCO_GL (egl, osmesa, glfw) to a backend that works.")


def _probe(backend: str) -> str | None:
    """Render a tiny model with ``MUJOCO_GL=backend`` in a fresh interpreter: None if it works, else why not."""
    env = dict(os.environ, MUJOCO_GL=backend)
    env.pop(CHOSEN_VAR, None)
    env.pop("PYOPENGL_PLATFORM", None)
    if backend in _PYOPENGL_PLATFORM:
        env["PYOPENGL_PLATFORM"] = _PYOPENGL_PLATFORM[backend]
    try:
        done = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True,
                              timeout=PROBE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return f"timed out after {PROBE_TIMEOUT_S:.0f} s"
    if done.returncode == 0:
        return None
    return _reason(done.stderr) or f"exit status {done.returncode}"


def _reason(stderr: str) -> str:
    # the exception that stopped the probe; tracebacks printed later (e.g. from __del__) are consequences
    lines = [line.strip() for line in stderr.splitlines() if line.strip()]
    errors = [line for line in lines if re.match(r"[\w.]+(Error|Exception|Exit)(:|$)", line)]
    if errors:
        return errors[0]
    return lines[-1] if lines else ""
