"""What the benchmark scripts share: timing calls with their host dispatch; writing JSON."""

from __future__ import annotations

import json
import os
import pathlib
import shlex
import sys
import time

import jax


def timed_calls(call, iters: int) -> tuple[float, float]:
    """(ms per call, host dispatch ms per call) of `call(i)` for i in range(iters), run to the
    end. Dispatch is the time the calls take to return: launching their work; where it nears
    the time per call, the launches, not the GPU, set the pace."""
    t0, dispatch, out = time.perf_counter(), 0.0, None
    for i in range(iters):
        t = time.perf_counter()
        out = call(i)
        dispatch += time.perf_counter() - t
    jax.block_until_ready(out)
    return (time.perf_counter() - t0) / iters * 1e3, dispatch / iters * 1e3


def save_json(result: dict, out: str | None, default: str | None = None) -> pathlib.Path | None:
    """Write `result` to `out` (or `default`), creating folders, with the command that made it
    and its provenance (commit, date, devices, versions: `dear_jax.provenance`) first; prints
    and returns the path. Nothing is written when neither is given.
    """
    path = out or default
    if not path:
        return None
    from dear_jax.provenance import MEASURED_ENV, provenance

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The command carries the variables that change what is measured.
    env = [f"{k}={shlex.quote(os.environ[k])}" for k in MEASURED_ENV if os.environ.get(k)]
    command = " ".join([*env, "python -m", _module(), shlex.join(sys.argv[1:])])
    head = {"command": command, **provenance()}
    path.write_text(json.dumps({**head, **result}, indent=1))
    print(f"wrote {path}")
    return path


def _module() -> str:
    """The running benchmark as `python -m` names it (benchmarks.<name>)."""
    main = pathlib.Path(sys.argv[0])
    return f"{main.parent.name}.{main.stem}" if main.parent.name == "benchmarks" else str(main)
