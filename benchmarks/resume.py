"""A real run killed with SIGKILL and resumed: how long the resume takes and what it restores.

    python -m benchmarks.resume --config walker_dear --seeds 3 --kill-after-frames 8000

Starts `run.py` as a user would, waits until it has written a checkpoint, kills it with
`kill -9` (no chance to save), starts the same command again and measures: the seconds from the
second start to its "resumed from checkpoint" log line and to its first training progress after
it, the replay rows read back and the replay's size on disk. The resumed run is then stopped with
SIGTERM (it checkpoints and exits). Prints a table and writes JSON (--out).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import signal
import subprocess
import sys
import tempfile
import time

from benchmarks.common import save_json
from dear_jax.logger import format_table

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _start(args, workdir: pathlib.Path) -> subprocess.Popen:
    cmd = [sys.executable, "run.py", "--config", args.config, "--workdir", str(workdir)]
    cmd += [
        f"--config.seeds={args.seeds}",
        f"--config.checkpoint_every_frames={args.kill_after_frames}",
        f"--config.log_every_frames={args.log_every}",
        f"--config.eval_every_frames={args.eval_every}",
        "--config.progress=False",
    ]
    cmd += [f"--config.{kv}" for kv in args.set]
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)


def _wait_for(path: pathlib.Path, pattern: str, after: int, proc, timeout: float):
    """Seconds until `pattern` appears in `path` past byte `after`, and the match."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout:
        text = path.read_text(errors="replace")[after:] if path.exists() else ""
        m = re.search(pattern, text)
        if m:
            return time.perf_counter() - t0, m
        if proc.poll() is not None:
            raise RuntimeError(
                f"run exited ({proc.returncode}) before {pattern!r}:\n{text[-3000:]}"
            )
        time.sleep(0.5)
    raise TimeoutError(f"no {pattern!r} in {path} after {timeout:.0f} s")


def _du(path: pathlib.Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--config", default="walker_dear")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--kill-after-frames", type=int, default=8000, help="checkpoint interval")
    parser.add_argument("--log-every", type=int, default=2000)
    parser.add_argument("--eval-every", type=int, default=10**9, help="default: frame 0 only")
    parser.add_argument("--set", nargs="*", default=[], help="more overrides: key=value ...")
    parser.add_argument("--timeout", type=float, default=400)
    parser.add_argument("--workdir", default=None)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    workdir = pathlib.Path(args.workdir or tempfile.mkdtemp(prefix="resume_"))
    log = workdir / "log.txt"

    first = _start(args, workdir)
    t0 = time.perf_counter()
    while not any(p.name.isdigit() for p in (workdir / "checkpoints").glob("*")):
        if first.poll() is not None or time.perf_counter() - t0 > args.timeout:
            raise RuntimeError(f"no checkpoint written:\n{log.read_text()[-3000:]}")
        time.sleep(0.5)
    t_ckpt = time.perf_counter() - t0
    print(f"first checkpoint after {t_ckpt:.0f} s; killing the run", flush=True)
    time.sleep(5)  # it trains on past the checkpoint, as a real crash would find it
    os.kill(first.pid, signal.SIGKILL)
    first.wait()
    killed_at = log.stat().st_size
    replay_bytes = _du(workdir / "replay") if (workdir / "replay").exists() else 0

    t0 = time.perf_counter()
    second = _start(args, workdir)
    t_resumed, m = _wait_for(
        log, r"resumed from checkpoint (\d+).*?(\d+) rows per seed", killed_at, second, args.timeout
    )
    print(f"resumed state restored after {t_resumed:.0f} s", flush=True)
    t_progress, _ = _wait_for(log, r"frame \d+ per seed: \d+ frames/s", killed_at, second, 300)
    second.send_signal(signal.SIGTERM)
    rc = second.wait(timeout=120)
    result = dict(
        config=args.config,
        seeds=args.seeds,
        first_checkpoint_s=t_ckpt,
        checkpoint_frame=int(m.group(1)),
        replay_rows_per_seed=int(m.group(2)),
        replay_on_disk_mb=replay_bytes / 2**20,
        resume_to_restored_s=t_resumed,
        resume_to_first_progress_s=t_progress,
        sigterm_exit_code=rc,
        wall_s=time.perf_counter() - t0,
    )
    print(format_table(["what", "value"], [[k, f"{v}"] for k, v in result.items()]))
    lines = log.read_text(errors="replace")[killed_at:].splitlines()
    print("\n".join(line for line in lines if " dear_jax:" in line))
    save_json(result, args.out)


if __name__ == "__main__":
    main()
