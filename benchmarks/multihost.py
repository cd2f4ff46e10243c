"""The multi-host path on one machine: P processes of `run.py --multihost` (`jax.distributed`, a
local coordinator), one GPU each, stand in for P hosts. The run is stopped by SIGTERM to one
process partway, resumed by the same commands, and trained to its end; its frames/s is set
against the one-process run of the same seeds on the same P GPUs (`config.devices=P`).

    python -m benchmarks.multihost                    # DEAR walker-walk, 2 processes x 1 seed,
                                                      # bf16, 16 envs per seed

Checks, and writes into the JSON: every process exits with 128 + SIGTERM at the stop and 0 at
the end; the stop leaves one checkpoint that every process saved at the same frame; the resumed
run ends at total_frames. Rates are the train-log rows after warm-up (`benchmarks/train.py`),
without the first row after the resume (restore and compilation). Writes
benchmarks/results/multihost_<platform>.json (or --out).

On a CPU-only machine (processes of one CPU device each; the figures mean nothing there):

    JAX_PLATFORMS=cpu python -m benchmarks.multihost --config configs/smoke.py --envs 2 \\
        --warmup-frames 80 --frames 160 --stop-at 160 --log-every 40 --capacity 1000 \\
        --out /tmp/multihost.json
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import signal
import socket
import subprocess
import sys
import tempfile
import time

import numpy as np

from benchmarks.common import save_json
from dear_jax.logger import read_csv

ROOT = pathlib.Path(__file__).resolve().parents[1]
# The runs' environment: this process's own, before main() keeps jax here from taking the GPUs'
# memory (it only reads the device kind and writes the JSON).
RUN_ENV = dict(os.environ)


def run_flags(args, seeds: int) -> list[str]:
    frames = args.warmup_frames + args.frames
    settings = {
        "seeds": seeds,
        "envs_per_seed": args.envs,
        "total_frames": frames,
        "log_every_frames": args.log_every,
        "eval_every_frames": 10 * frames,  # the untrained policy's and the closing evaluations
        "num_eval_episodes": 1,
        "checkpoint_every_frames": 0,  # the stop's checkpoint and the end's
        "save_video": False,
        "progress": False,
        "agent.compute_dtype": args.dtype,
        "replay.capacity": args.capacity,
        "replay.seed_frames": args.warmup_frames // 2,
        "env.episode_frames": 0,
    }
    return [f"--config={args.config}", *(f"--config.{k}={v}" for k, v in settings.items())]


def launch(args, workdir: pathlib.Path, port: int) -> list[subprocess.Popen]:
    """The P processes of one multi-host run, process i on GPU i (on CPU: its own CPU device)."""
    procs = []
    for i in range(args.processes):
        env = dict(
            RUN_ENV,
            JAX_COORDINATOR_ADDRESS=f"localhost:{port}",
            JAX_NUM_PROCESSES=str(args.processes),
            JAX_PROCESS_ID=str(i),
            CUDA_VISIBLE_DEVICES=str(i),
            JAX_CPU_COLLECTIVES_IMPLEMENTATION="gloo",
        )
        flags = run_flags(args, args.processes * args.seeds_per_process)
        procs.append(
            subprocess.Popen(
                [sys.executable, "run.py", *flags, f"--workdir={workdir}"],
                cwd=ROOT,
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=open(workdir.parent / f"{workdir.name}.{i}.err", "a"),  # noqa: SIM115
            )
        )
    return procs


def wait_all(procs, timeout: float) -> list[int]:
    deadline = time.monotonic() + timeout
    codes = []
    for p in procs:
        try:
            codes.append(p.wait(max(1.0, deadline - time.monotonic())))
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            raise
    return codes


def last_frame(workdir: pathlib.Path) -> int:
    path = workdir / "seed_0" / "train.csv"
    try:
        return int(read_csv(path)["frame"][-1])
    except (FileNotFoundError, KeyError, IndexError, ValueError):
        return 0


def rates(workdir: pathlib.Path, args, skip_after: int | None = None) -> dict:
    """Aggregate env frames/s of the rows after warm-up (and not the first after `skip_after`)."""
    rows = read_csv(workdir / "seed_0" / "train.csv")
    frames, fps = rows["frame"], rows["fps"]
    keep = frames > args.warmup_frames + args.log_every
    if skip_after is not None:
        keep &= ~((frames > skip_after) & (frames <= skip_after + args.log_every))
    return dict(aggregate_fps=float(np.mean(fps[keep])), fps_rows=fps[keep].tolist())


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--config", default="configs/walker_dear.py")
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--seeds-per-process", type=int, default=1)
    p.add_argument("--envs", type=int, default=16)
    p.add_argument("--dtype", default="bfloat16", choices=["float32", "bfloat16"])
    p.add_argument("--warmup-frames", type=int, default=4000)
    p.add_argument("--frames", type=int, default=16_000, help="measured frames per seed")
    p.add_argument("--stop-at", type=int, default=10_000, help="SIGTERM after this frame")
    p.add_argument("--stop-process", type=int, default=1, help="which process gets SIGTERM")
    p.add_argument("--log-every", type=int, default=2000)
    p.add_argument("--capacity", type=int, default=100_000)
    p.add_argument("--timeout", type=float, default=900, help="seconds per phase")
    p.add_argument("--skip-single", action="store_true", help="no one-process comparison run")
    p.add_argument("--out", default=None)
    args = p.parse_args()

    result = dict(
        config=args.config,
        processes=args.processes,
        seeds_per_process=args.seeds_per_process,
        envs_per_seed=args.envs,
        dtype=args.dtype,
        warmup_frames=args.warmup_frames,
        frames_per_seed=args.frames,
    )
    os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    import jax

    platform = jax.devices()[0].platform
    out_default = f"benchmarks/results/multihost_{platform}.json"
    with tempfile.TemporaryDirectory() as tmp:
        workdir = pathlib.Path(tmp) / "multihost"
        workdir.mkdir()
        t0 = time.monotonic()
        procs = launch(args, workdir, free_port())
        while last_frame(workdir) < args.stop_at and all(q.poll() is None for q in procs):
            time.sleep(1.0)
        procs[args.stop_process].send_signal(signal.SIGTERM)
        stop_codes = wait_all(procs, args.timeout)
        steps = [
            sorted(int(f.stem) for f in (workdir / f"checkpoints_process_{i}").glob("*.json"))
            for i in range(args.processes)
        ]
        stop_frame = steps[0][-1] if steps[0] else None
        host_state = workdir / "checkpoints_process_0" / f"{stop_frame}.json"
        stopped = json.loads(host_state.read_text()) if stop_frame is not None else {}
        t1 = time.monotonic()
        procs = launch(args, workdir, free_port())
        end_codes = wait_all(procs, args.timeout)
        summary = json.loads((workdir / "summary.json").read_text())
        result["multihost"] = dict(
            stop_exit_codes=stop_codes,
            checkpoint_frames_per_process=steps,
            stop_frame=stop_frame,
            stopped_counters=stopped.get("counters"),
            end_exit_codes=end_codes,
            frames_per_seed_at_end=summary["frames_per_seed"],
            processes_in_summary=summary["processes"],
            devices_in_summary=summary["devices"],
            wall_s_first_part=t1 - t0,
            wall_s_resumed_part=time.monotonic() - t1,
            **rates(workdir, args, skip_after=stop_frame),
        )
        ok = (
            all(c == 128 + signal.SIGTERM for c in stop_codes)
            and all(s and s[-1] == stop_frame for s in steps)
            and end_codes == [0] * args.processes
            and summary["frames_per_seed"] == args.warmup_frames + args.frames
        )
        result["multihost"]["checks_passed"] = bool(ok)
        save_json(result, args.out, out_default)
        if not args.skip_single:
            single = pathlib.Path(tmp) / "single"
            flags = run_flags(args, args.processes * args.seeds_per_process)
            flags.append(f"--config.devices={args.processes}")
            env = dict(RUN_ENV, CUDA_VISIBLE_DEVICES=",".join(map(str, range(args.processes))))
            env.pop("JAX_COORDINATOR_ADDRESS", None)
            if platform == "cpu":
                env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={args.processes}"
            subprocess.run(
                [sys.executable, "run.py", *flags, f"--workdir={single}"],
                cwd=ROOT,
                env=env,
                check=True,
                stdout=subprocess.DEVNULL,
                timeout=args.timeout,
            )
            result["one_process"] = rates(single, args)
            result["multihost_over_one_process"] = (
                result["multihost"]["aggregate_fps"] / result["one_process"]["aggregate_fps"]
            )
        save_json(result, args.out, out_default)
    m = result["multihost"]
    print(
        f"\n{args.processes} processes x {args.seeds_per_process} seeds: stop at frame "
        f"{m['stop_frame']} (exit codes {m['stop_exit_codes']}), resumed to "
        f"{m['frames_per_seed_at_end']} (exit codes {m['end_exit_codes']}); checks passed: "
        f"{m['checks_passed']}\n{m['aggregate_fps']:.0f} env frames/s in all"
        + (
            f" against {result['one_process']['aggregate_fps']:.0f} in one process "
            f"({result['multihost_over_one_process']:.2f}x)"
            if "one_process" in result
            else ""
        )
    )
    return 0 if m["checks_passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
