"""Where a run or a figure comes from: the code's commit, the date, the machine's accelerator and
the versions of the libraries that computed it. Written into every run's summary and every
benchmark's JSON.

The commit is `DEAR_JAX_COMMIT` from the environment when set (a copy of the tree sent to another
machine, whose `.git`, if any, need not match it), else git's (`git rev-parse HEAD`, with
"+dirty" when tracked files differ from it), else "unknown".
"""

from __future__ import annotations

import datetime
import functools
import os
import pathlib
import platform
import subprocess

ROOT = pathlib.Path(__file__).resolve().parents[1]


@functools.cache
def commit() -> str:
    if os.environ.get("DEAR_JAX_COMMIT"):
        return os.environ["DEAR_JAX_COMMIT"]
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, timeout=10
        )
        if head.returncode == 0:
            dirty = subprocess.run(
                ["git", "status", "--porcelain", "--untracked-files=no"],
                cwd=ROOT,
                capture_output=True,
                text=True,
                timeout=10,
            ).stdout.strip()
            return head.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return "unknown"


# Environment variables that change what a run or benchmark measures: XLA_FLAGS (what the
# programs compile to) and MUJOCO_EGL_DEVICE_ID (the GPU the render workers draw on).
MEASURED_ENV = ("XLA_FLAGS", "MUJOCO_EGL_DEVICE_ID")


def provenance() -> dict:
    """commit, date (UTC), the devices JAX sees, the versions of python, jax, flax, mujoco, and
    where set XLA_FLAGS (they change the compiled program) and MUJOCO_EGL_DEVICE_ID (the GPU
    that draws the frames, by default the first the process sees)."""
    import flax
    import jax
    import mujoco

    device = jax.devices()[0]
    return dict(
        commit=commit(),
        date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        platform=device.platform,
        device_kind=device.device_kind,
        device_count=jax.device_count(),
        process_count=jax.process_count(),
        python=platform.python_version(),
        jax=jax.__version__,
        flax=flax.__version__,
        mujoco=mujoco.__version__,
        **{k.lower(): os.environ[k] for k in MEASURED_ENV if os.environ.get(k)},
    )
