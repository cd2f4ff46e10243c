"""Where the training loop's time goes: a profile of real iterations, per program.

    python -m benchmarks.profile_loop --config configs/walker_dear.py --seeds 5 --envs 16 \
        --dtype bfloat16 --iterations 20

Runs `dear_jax.train.train` (as `benchmarks/train.py` does) with `config.profile` set to trace
`--iterations` loop iterations after warm-up, then reads the trace back with
`jax.profiler.ProfileData` and prints, per iteration: the wall time, the time the GPU was busy
(the union of its kernels over all streams) and idle, the GPU time of each compiled program
(learn, act, physics, the env's device half, ...), the slowest kernels, and the host threads'
busiest trace events (where the Python side waits). Writes JSON (--out).
"""

from __future__ import annotations

import argparse
import collections
import pathlib
import tempfile

import jax

from benchmarks.common import save_json
from benchmarks.train import add_run_arguments, bench_config, drawn_beside_lanes
from dear_jax import train
from dear_jax.logger import read_csv


def trace_events(trace_dir: pathlib.Path):
    """(plane, line, name, stats, start_ns, end_ns) of every event of the newest trace."""
    from jax.profiler import ProfileData

    files = sorted(trace_dir.rglob("*.xplane.pb"), key=lambda f: f.stat().st_mtime)
    if not files:
        raise FileNotFoundError(f"no trace under {trace_dir}")
    for plane in ProfileData.from_file(str(files[-1])).planes:
        for line in plane.lines:
            for ev in line.events:
                yield plane.name, line.name, ev.name, dict(ev.stats), ev.start_ns, ev.end_ns


def busy_ns(intervals) -> int:
    """Length of the union of [start, end) intervals."""
    total, reach = 0, None
    for start, end in sorted(intervals):
        if reach is None or start > reach:
            total += end - start
            reach = end
        elif end > reach:
            total += end - reach
            reach = end
    return total


def summarise(trace_dir: pathlib.Path, iterations: int, top: int) -> dict:
    gpu, host = [], []
    for plane, line, name, stats, start, end in trace_events(trace_dir):
        if plane.startswith("/device:GPU") and line.startswith("Stream"):
            module = str(stats.get("hlo_module") or "?")
            gpu.append((module, name, str(stats.get("hlo_op", "")), start, end))
        elif plane.startswith("/host:CPU"):
            host.append((line, name, start, end))
    everything = [(s, e) for *_, s, e in gpu] + [(s, e) for *_, s, e in host]
    span = max(e for _, e in everything) - min(s for s, _ in everything)
    per = 1e-6 / iterations  # ns over the trace -> ms per iteration
    modules, kernels, launches = collections.Counter(), collections.Counter(), collections.Counter()
    for module, name, op, start, end in gpu:
        modules[module] += end - start
        launches[module] += 1
        kernels[f"{module} | {op or name[:60]}"] += end - start
    busy = busy_ns([(s, e) for *_, s, e in gpu])
    host_names, host_counts = collections.Counter(), collections.Counter()
    for line, name, start, end in host:
        key = f"{line[:24]} | {name[:70]}"
        host_names[key] += end - start
        host_counts[key] += 1
    return dict(
        iterations=iterations,
        wall_ms=span * per,
        gpu_busy_ms=busy * per,
        gpu_idle_ms=(span - busy) * per,
        programs={
            m: dict(ms=ns * per, kernels=launches[m] / iterations)
            for m, ns in modules.most_common()
        },
        kernels={k: ns * per for k, ns in kernels.most_common(top)},
        host_events={
            k: dict(ms=ns * per, calls=host_counts[k] / iterations)
            for k, ns in host_names.most_common(top)
        },
    )


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    add_run_arguments(p)
    p.add_argument("--iterations", type=int, default=20, help="loop iterations traced")
    p.add_argument("--top", type=int, default=25)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    config = drawn_beside_lanes(bench_config(args))
    config.replay.disk = False
    # Two log rows after warm-up (updates compiled and running) give the untraced rate.
    config.profile.at_frame = args.warmup_frames + 2 * args.log_every
    frames_per_iteration = config.env.action_repeat * config.envs_per_seed
    config.total_frames = config.profile.at_frame + (args.iterations + 2) * frames_per_iteration
    config.profile.iterations = args.iterations
    with tempfile.TemporaryDirectory() as workdir:
        train.train(config, workdir)
        result = summarise(pathlib.Path(workdir) / "profile", args.iterations, args.top)
        rows = read_csv(pathlib.Path(workdir) / "seed_0" / "train.csv")
    untraced = rows["fps"][
        (rows["frame"] > args.warmup_frames) & (rows["frame"] <= config.profile.at_frame)
    ]
    result["untraced_fps_rows"] = untraced.tolist()
    device = jax.devices()[0].device_kind
    print(
        f"{args.config}, {args.seeds} seeds x {args.envs} envs, {args.dtype}, {device}: per "
        f"iteration {result['wall_ms']:.1f} ms wall, GPU busy {result['gpu_busy_ms']:.1f} ms, "
        f"idle {result['gpu_idle_ms']:.1f} ms ({args.iterations} iterations traced); untraced "
        f"env frames/s in all before the trace: {result['untraced_fps_rows']}"
    )
    print("\n| program | GPU ms per iteration | kernels per iteration |\n|---|---:|---:|")
    for m, v in result["programs"].items():
        print(f"| {m} | {v['ms']:.2f} | {v['kernels']:.0f} |")
    print("\n| program / op | GPU ms per iteration |\n|---|---:|")
    for k, ms in result["kernels"].items():
        print(f"| {k} | {ms:.3f} |")
    print("\n| host thread / event | ms per iteration | calls |\n|---|---:|---:|")
    for k, v in result["host_events"].items():
        print(f"| {k} | {v['ms']:.2f} | {v['calls']:.1f} |")
    save_json(
        dict(device=device, jax=jax.__version__, args=vars(args), **result),
        args.out,
        "benchmarks/results/profile_loop_gpu.json",
    )


if __name__ == "__main__":
    main()
