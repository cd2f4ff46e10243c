"""Scaling over devices: aggregate env frames/s with the seeds split over 1, 2, ... devices.

    python -m benchmarks.scaling                       # DEAR walker-walk, 1 and 3 seeds per GPU,
                                                       # on 1 and 2 GPUs, bf16, 16 envs per seed
    python -m benchmarks.scaling --devices 1 2 4 --seeds-per-device 1 3

For each seeds-per-device count K and device count N, a run of N x K seeds with
`config.devices = N` (the seeds split over the first N devices, one render pool on the host
drawing on those N GPUs) is
measured as `benchmarks/train.py` measures a run: the real training loop, the rates of its
train-log rows after warm-up. Scaling efficiency = fps(N) / (N x fps(1)) at the same K: 1 when
every device trains its seeds as fast as one device alone trains its own. The defaults are the
trainer's on a GPU: the config's conv stack ("auto": the Pallas stacks), bf16, 16 envs per seed.
Prints a table and writes JSON (with commit, conv stack, dtype, device kind) to
benchmarks/results/scaling_<platform>.json (or --out).

On a CPU-only machine the code path can be tried with virtual devices (the figures mean nothing
there: the devices share the same cores):

    XLA_FLAGS=--xla_force_host_platform_device_count=2 JAX_PLATFORMS=cpu \\
        python -m benchmarks.scaling --config configs/smoke.py --seeds-per-device 1 --envs 2 \\
        --warmup-frames 80 --frames 80 --log-every 40 --capacity 1000 --out /tmp/scaling.json
"""

from __future__ import annotations

import argparse
import logging

import jax

from benchmarks.common import save_json
from benchmarks.train import add_run_arguments, bench_config, throughput
from dear_jax import networks
from dear_jax.logger import format_table
from dear_jax.provenance import commit


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    add_run_arguments(p)
    p.set_defaults(envs=16, dtype="bfloat16", frames=16_000)
    p.add_argument("--devices", type=int, nargs="+", default=[1, 2], help="device counts")
    p.add_argument("--seeds-per-device", type=int, nargs="+", default=[1, 3])
    p.add_argument("--out", default=None)
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    available = jax.local_device_count()
    if max(args.devices) > available:
        p.error(f"--devices {max(args.devices)} but {available} device(s) exist here")
    device = jax.devices()[0]
    args.seeds = args.seeds_per_device[0]
    result = dict(
        config=args.config,
        conv_stack=networks.stack_for(bench_config(args).agent.conv_stack),
        dtype=args.dtype,
        envs_per_seed=args.envs,
        warmup_frames=args.warmup_frames,
        frames_per_seed=args.frames,
        runs=[],
    )
    rows = []
    for k in args.seeds_per_device:
        base = None
        for n in args.devices:
            args.seeds = n * k
            config = bench_config(args)
            config.devices = n
            tp = throughput(config, args.warmup_frames)
            run = dict(devices=n, seeds_per_device=k, seeds=args.seeds, **tp)
            if n == 1:
                base = tp["aggregate_fps"]
            if base is not None:
                run["efficiency"] = tp["aggregate_fps"] / (n * base)
            result["runs"].append(run)
            rows.append(
                [
                    n,
                    k,
                    args.seeds,
                    f"{tp['aggregate_fps']:.0f}",
                    f"{tp['aggregate_fps'] / n:.0f}",
                    f"{run['efficiency']:.2f}" if "efficiency" in run else "",
                ]
            )
            save_json(result, args.out, f"benchmarks/results/scaling_{device.platform}.json")
    print(
        f"\nScaling over {device.device_kind} devices: {config.agent.method} on "
        f"{config.env.task}, {args.envs} envs per seed, {args.dtype}, {result['conv_stack']} "
        f"conv stacks (commit {commit()})"
    )
    columns = ["devices", "seeds per device", "seeds", "env frames/s", "per device", "efficiency"]
    print(format_table(columns, rows))


if __name__ == "__main__":
    main()
