"""Every benchmark's JSON (`benchmarks.common.save_json`) starts with the command that made it,
as one would type it again, and where it comes from."""

import json
import sys

from benchmarks.common import save_json


def test_the_command_reruns_as_typed_with_its_xla_flags(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["benchmarks/update.py", "--seeds", "1", "5"])
    # Flags XLA knows: provenance() may start jax's backend, which parses them.
    flags = "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
    monkeypatch.setenv("XLA_FLAGS", flags)
    path = save_json({"rows": [1]}, str(tmp_path / "a" / "flags.json"))
    result = json.loads(path.read_text())
    assert result["command"] == f"XLA_FLAGS='{flags}' python -m benchmarks.update --seeds 1 5"
    assert result["xla_flags"] == flags and result["rows"] == [1]
    assert {"commit", "date", "device_kind", "jax"} <= set(result)

    monkeypatch.delenv("XLA_FLAGS")
    result = json.loads(save_json({}, str(tmp_path / "plain.json")).read_text())
    assert result["command"] == "python -m benchmarks.update --seeds 1 5"
    assert "xla_flags" not in result
