"""Scaling over devices: aggregate env frames/s with the seeds split over 1, 2, ... devices.

    python -m benchmarks.scaling --config configs/walker_dear.py --devices 1 2 \
        --seeds-per-device 5 --envs 8 --warmup-frames 2400 --frames 8000 --log-every 1600

Each device count N trains N x `--seeds-per-device` seeds with `config.devices = N` (the seeds
split over the first N devices, one render pool on the host) and is measured as
`benchmarks/train.py` measures a run: the real training loop, the rates of its train-log rows
after warm-up. Scaling efficiency of N devices = fps(N) / (N x fps(1)): 1 when every device
trains its seeds as fast as one device alone trains its own.
Prints a table and writes JSON to benchmarks/results/scaling_<platform>.json (or --out).

On a CPU-only machine the code path can be tried with virtual devices (the figures mean nothing
there: the devices share the same cores):

    XLA_FLAGS=--xla_force_host_platform_device_count=2 JAX_PLATFORMS=cpu \
        python -m benchmarks.scaling --config configs/smoke.py --seeds-per-device 1 --envs 2 \
        --warmup-frames 80 --frames 80 --log-every 40 --capacity 1000 --out /tmp/scaling.json
"""

from __future__ import annotations

import argparse
import logging

import jax

from benchmarks.common import save_json
from benchmarks.train import add_run_arguments, bench_config, throughput
from dear_jax.logger import format_table


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    add_run_arguments(p)
    p.add_argument("--devices", type=int, nargs="+", default=[1, 2], help="device counts")
    p.add_argument("--seeds-per-device", type=int, default=5)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    available = jax.local_device_count()
    if max(args.devices) > available:
        p.error(f"--devices {max(args.devices)} but {available} device(s) exist here")
    device = jax.devices()[0]
    result = dict(
        device=device.device_kind,
        platform=device.platform,
        config=args.config,
        seeds_per_device=args.seeds_per_device,
        envs_per_seed=args.envs,
        dtype=args.dtype,
        frames_per_seed=args.frames,
        runs=[],
    )
    rows = []
    for n in args.devices:
        args.seeds = n * args.seeds_per_device
        config = bench_config(args)
        config.devices = n
        tp = throughput(config, args.warmup_frames)
        run = dict(devices=n, seeds=args.seeds, **tp)
        base = result["runs"][0] if result["runs"] and result["runs"][0]["devices"] == 1 else None
        if base is not None:
            run["efficiency"] = tp["aggregate_fps"] / (n * base["aggregate_fps"])
        elif n == 1:
            run["efficiency"] = 1.0
        result["runs"].append(run)
        rows.append(
            [
                n,
                args.seeds,
                f"{tp['aggregate_fps']:.0f}",
                f"{tp['aggregate_fps'] / n:.0f}",
                f"{run['efficiency']:.2f}" if "efficiency" in run else "",
            ]
        )
        save_json(result, args.out, f"benchmarks/results/scaling_{device.platform}.json")
    print(
        f"\nScaling over {device.device_kind} devices: {config.agent.method} on "
        f"{config.env.task}, {args.seeds_per_device} seeds per device x {args.envs} envs"
    )
    columns = ["devices", "seeds", "env frames/s", "per device", "efficiency"]
    print(format_table(columns, rows))


if __name__ == "__main__":
    main()
