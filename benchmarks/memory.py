"""Accelerator memory per seed, by component, for each method, and how many seeds fit.

    python -m benchmarks.memory [--methods dear drqv2 sear ted] [--batch 512] [--seeds 1 5]
        [--capacity 250000] [--dtype bfloat16] [--check dear] [--out FILE]

Per seed a run keeps on the accelerator its parameters, the Adam moments of its two optimisers
(learner: encoder + critic + heads; actor), the target critic, and its replay (`capacity`
entries of `replay.entry_bytes`: frame, mask, action, reward, discount, episode id). The learn
program adds temporaries: XLA's memory analysis of the compiled S-seed update as runs compile it
(`agent.seed_axis` "hybrid", `agent.conv_stack` "auto": the Pallas stacks on GPUs). They grow
with S, so they are measured at each --seeds and extended linearly from the smallest and the
largest. "Seeds that fit" is the largest S with S x (agent + replay) + temporaries(S) within
JAX's pool on the device (its `bytes_limit`; on a CPU, free RAM). Acting, the env's arrays and
an evaluation on the accelerator come on top; they are small beside these (`run.py` checks the
replay against the free memory before it allocates it).

--check METHOD allocates the seeds that fit, each with its agent and a replay of --capacity
entries, and runs updates, which fails with an out-of-memory error if the table is wrong; it
records the device's peak.
Prints a table and writes JSON (benchmarks/results/memory_<platform>.json by default).
"""

from __future__ import annotations

import argparse

import jax

from benchmarks.common import save_json
from benchmarks.update import update_setup
from dear_jax import replay, update

GIB, MIB = 2**30, 2**20
FRAME = (84, 84, 3)
ACTION_DIM = 6  # walker


def _bytes(tree) -> int:
    return sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(tree))


def _setup(method: str, seeds: int, args):
    stack = "pallas" if jax.default_backend() == "gpu" else "xla"
    return update_setup(
        method, seeds, args.batch, args.dtype, "hybrid", ACTION_DIM, conv_stack=stack
    )


def measure(method: str, args, limit: int) -> dict:
    """Per-seed components, temporaries at each seed count, and the seeds that fit."""
    temps = {}
    for seeds in sorted(args.seeds):
        step, states, batches, hp = _setup(method, seeds, args)
        keys = jax.random.split(jax.random.key(0), seeds)
        analysis = step.lower(states, batches, keys, hp).compile().memory_analysis()
        temps[seeds] = analysis.temp_size_in_bytes + _bytes(batches)
        if seeds == min(args.seeds):
            per_seed = {
                "parameters": _bytes(states.params) // seeds,
                "adam_moments": (_bytes(states.opt_state) + _bytes(states.actor_opt_state))
                // seeds,
                "target_critic": _bytes(states.target_critic) // seeds,
            }
        del states, batches
    lo, hi = min(temps), max(temps)
    slope = (temps[hi] - temps[lo]) / (hi - lo) if hi > lo else temps[lo] / lo
    temp_at = lambda s: temps[lo] + slope * (s - lo)  # noqa: E731
    agent = sum(per_seed.values())
    replay_seed = args.capacity * replay.entry_bytes(FRAME, ACTION_DIM)
    fits = 0
    while (fits + 1) * (agent + replay_seed) + temp_at(fits + 1) <= limit:
        fits += 1
    # The largest replay per seed beside the agents at the largest seed count measured.
    capacity_at_hi = int(
        (limit - hi * agent - temp_at(hi)) // (hi * replay.entry_bytes(FRAME, ACTION_DIM))
    )
    return dict(
        method=method,
        per_seed_bytes={**per_seed, "agent": agent, "replay": replay_seed},
        update_temporaries_bytes={str(s): int(t) for s, t in temps.items()},
        temporaries_per_extra_seed_bytes=int(slope),
        seeds_that_fit=fits,
        max_capacity_per_seed_at_seeds={str(hi): max(capacity_at_hi, 0)},
    )


def check(row: dict, args) -> dict:
    """Allocate the replays and agents the row says fit, run updates, read the device's peak."""
    seeds = row["seeds_that_fit"]
    step, states, batches, hp = _setup(row["method"], seeds, args)
    buffer = replay.init(args.capacity, 8, FRAME, ACTION_DIM, leading=(seeds,))
    for i in range(3):
        states, metrics = step(states, batches, jax.random.split(jax.random.key(i), seeds), hp)
    jax.block_until_ready((metrics, buffer))
    stats = jax.devices()[0].memory_stats() or {}
    return dict(seeds=seeds, peak_gib=stats.get("peak_bytes_in_use", 0) / GIB)


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--methods", nargs="+", default=list(update.METHODS))
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--dtype", default="bfloat16", choices=["float32", "bfloat16"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 5])
    parser.add_argument("--capacity", type=int, default=250_000, help="replay entries per seed")
    parser.add_argument("--check", default=None, choices=update.METHODS)
    parser.add_argument("--limit-gib", type=float, default=None, help="instead of the device's")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    device = jax.devices()[0]
    limit = (device.memory_stats() or {}).get("bytes_limit") or replay.available_bytes(device)
    limit = int(args.limit_gib * GIB) if args.limit_gib else limit
    rows = [measure(m, args, limit) for m in args.methods]
    if args.check:
        row = next((r for r in rows if r["method"] == args.check), None)
        if row is None or not row["seeds_that_fit"]:
            raise SystemExit(f"--check {args.check}: give it in --methods, with a seed that fits")
        row["check"] = check(row, args)

    hi = max(args.seeds)
    print(
        f"\n{device.device_kind}: {limit / GIB:.1f} GiB for JAX; batch {args.batch}, {args.dtype}; "
        f"replay {args.capacity:,} entries per seed\n"
        "| method | parameters MiB | Adam moments MiB | target critic MiB | replay GiB "
        f"| update temporaries GiB (1 seed / +1 seed) | seeds that fit |\n"
        "|---|---:|---:|---:|---:|---:|---:|"
    )
    for r in rows:
        b = r["per_seed_bytes"]
        t1 = r["update_temporaries_bytes"][str(min(args.seeds))]
        print(
            f"| {r['method']} | {b['parameters'] / MIB:.0f} | {b['adam_moments'] / MIB:.0f} "
            f"| {b['target_critic'] / MIB:.1f} | {b['replay'] / GIB:.2f} "
            f"| {t1 / GIB:.2f} / {r['temporaries_per_extra_seed_bytes'] / GIB:.2f} "
            f"| {r['seeds_that_fit']} |"
        )
        if "check" in r:
            c = r["check"]
            print(
                f"check ({r['method']}): {c['seeds']} seeds x {args.capacity:,} entries allocated, "
                f"updates ran; peak {c['peak_gib']:.1f} GiB"
            )
    save_json(
        dict(
            device=device.device_kind,
            limit_gib=limit / GIB,
            entry_bytes=replay.entry_bytes(FRAME, ACTION_DIM),
            max_seeds_measured=hi,
            args=vars(args),
            rows=rows,
        ),
        args.out,
        f"benchmarks/results/memory_{device.platform}.json",
    )


if __name__ == "__main__":
    main()
