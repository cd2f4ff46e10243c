"""Every benchmark's JSON (`benchmarks.common.save_json`) starts with the command that made it,
as one would type it again, and where it comes from."""

import json
import os
import sys

from benchmarks.common import save_json


def test_the_command_reruns_as_typed_with_its_xla_flags_and_egl_device(tmp_path, monkeypatch):
    argv = ["--seeds", "1", "5", "--set", "agent.kernels=BLOCK=64 STAGES=2"]
    monkeypatch.setattr(sys, "argv", ["benchmarks/update.py", *argv])
    # The test run's own flags (conftest.py: several, so the command must quote them), left as
    # they are: jax's backend, if provenance() starts it here, parses them.
    flags = os.environ["XLA_FLAGS"]
    assert " " in flags
    path = save_json({"rows": [1]}, str(tmp_path / "a" / "flags.json"))
    result = json.loads(path.read_text())
    args = "--seeds 1 5 --set 'agent.kernels=BLOCK=64 STAGES=2'"
    assert result["command"] == f"XLA_FLAGS='{flags}' python -m benchmarks.update {args}"
    assert result["xla_flags"] == flags and result["rows"] == [1]
    assert {"commit", "date", "device_kind", "jax"} <= set(result)

    monkeypatch.setenv("MUJOCO_EGL_DEVICE_ID", "1")
    result = json.loads(save_json({}, str(tmp_path / "egl.json")).read_text())
    with_egl = f"XLA_FLAGS='{flags}' MUJOCO_EGL_DEVICE_ID=1 python -m benchmarks.update {args}"
    assert result["command"] == with_egl

    monkeypatch.delenv("XLA_FLAGS")
    monkeypatch.delenv("MUJOCO_EGL_DEVICE_ID")
    result = json.loads(save_json({}, str(tmp_path / "plain.json")).read_text())
    assert result["command"] == f"python -m benchmarks.update {args}"
    assert "xla_flags" not in result


def test_the_update_benchmarks_digest_sums_float_leaves_and_tells_states_apart():
    import jax.numpy as jnp
    import numpy as np

    from benchmarks.update import state_digest

    # Integer leaves (step counters) are not values of the arithmetic and are left out.
    tree = {"w": jnp.array([1.5, -0.25], jnp.bfloat16), "b": np.float32(2.0), "n": jnp.arange(7)}
    assert state_digest(tree) == 3.25
    # A change in one weight's last place changes the digest.
    nudged = {**tree, "b": np.nextafter(np.float32(2.0), np.float32(3.0))}
    assert state_digest(nudged) != state_digest(tree)
