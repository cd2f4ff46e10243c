"""Environments: DMC and Franka Kitchen tasks on MJX or CPU MuJoCo, rendered by a CPU worker pool.

`envs.make(name, ...)` builds a batched `Env` (envs/base.py); `envs.names()` lists the tasks.
"""

import os

# Before mujoco is imported anywhere: render workers and previews use EGL unless told otherwise.
os.environ.setdefault("MUJOCO_GL", "egl")

import logging  # noqa: E402

import mujoco  # noqa: E402

# MuJoCo's warnings (an unstable simulation, a full contact buffer) go to Python's log, in every
# process that imports envs (render workers too), instead of a MUJOCO_LOG.TXT in the working
# directory.
mujoco.set_mju_user_warning(lambda text: logging.getLogger("mujoco").warning("MuJoCo: %s", text))

from envs.base import Env, EnvSpec, EnvState, TimeStep  # noqa: E402
from envs.physics import SolverSettings  # noqa: E402
from envs.registry import frames_per_episode, make, names, register  # noqa: E402
from envs.render import RenderSettings  # noqa: E402

__all__ = [
    "Env",
    "EnvSpec",
    "EnvState",
    "RenderSettings",
    "SolverSettings",
    "TimeStep",
    "make",
    "names",
    "frames_per_episode",
    "register",
]
