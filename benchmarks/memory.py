"""How many seeds x replay entries fit on this accelerator, measured and then checked by allocating.

    python -m benchmarks.memory [--method dear] [--batch 512] [--seeds 1 3 5 10] [--check-seeds 5]

Per seed the GPU holds its agent (parameters, Adam moments, target critic) and its replay (single
frames + masks + actions/rewards/discounts/episode ids: `replay.entry_bytes`); the update adds its
temporaries (XLA's memory analysis of the compiled S-seed update). What the device reports as its
limit, less those, divided by the entry size gives the largest capacity per seed. The check then
allocates the replay at that capacity for --check-seeds seeds (less 5% margin) beside the agents
and runs updates, which fails with an out-of-memory error if the figure is wrong.
Prints a table and writes JSON (benchmarks/results/memory_<platform>.json).
"""

from __future__ import annotations

import argparse

import jax

from benchmarks.common import save_json
from benchmarks.update import update_setup
from dear_jax import replay, update

GIB = 2**30
FRAME = (84, 84, 3)


def _bytes(tree) -> int:
    return sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(tree))


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--method", default="dear", choices=update.METHODS)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--dtype", default="bfloat16", choices=["float32", "bfloat16"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 3, 5, 10])
    parser.add_argument("--check-seeds", type=int, default=5)
    parser.add_argument("--limit-gib", type=float, default=None, help="instead of the device's")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    device = jax.devices()[0]
    limit = (device.memory_stats() or {}).get("bytes_limit") or replay.available_bytes(device)
    limit = int(args.limit_gib * GIB) if args.limit_gib else limit
    entry = replay.entry_bytes(FRAME, 6)
    rows = []
    for seeds in args.seeds:
        step, states, batches, hp = update_setup(args.method, seeds, args.batch, args.dtype, "loop")
        keys = jax.random.split(jax.random.key(0), seeds)
        analysis = step.lower(states, batches, keys, hp).compile().memory_analysis()
        temp = analysis.temp_size_in_bytes
        agent = _bytes(states)
        free = limit - agent - temp - _bytes(batches)
        capacity = free // (seeds * entry)
        rows.append(
            dict(
                seeds=seeds,
                agent_gib=agent / GIB,
                update_temp_gib=temp / GIB,
                max_capacity_per_seed=int(capacity),
                max_entries_in_all=int(capacity * seeds),
            )
        )
        print(rows[-1])
        del states, batches
    check = next((r for r in rows if r["seeds"] == args.check_seeds), None)
    if check:
        seeds, capacity = check["seeds"], int(0.95 * check["max_capacity_per_seed"])
        step, states, batches, hp = update_setup(args.method, seeds, args.batch, args.dtype, "loop")
        buffer = replay.init(capacity, 8, FRAME, 6, leading=(seeds,))
        for i in range(3):
            states, metrics = step(states, batches, jax.random.split(jax.random.key(i), seeds), hp)
        jax.block_until_ready((metrics, buffer))
        check["checked_capacity_per_seed"] = capacity
        check["peak_gib"] = (device.memory_stats() or {}).get("peak_bytes_in_use", 0) / GIB
    print(
        f"\n{device.device_kind}: {limit / GIB:.1f} GiB for JAX, {entry:,} bytes per replay entry "
        f"({args.method}, batch {args.batch}, {args.dtype})\n"
        "| seeds | agent GiB | update temporaries GiB | max replay entries per seed | checked |\n"
        "|---:|---:|---:|---:|---|"
    )
    for r in rows:
        checked = (
            f"{r['checked_capacity_per_seed']:,} allocated + updates ran "
            f"(peak {r['peak_gib']:.1f} GiB)"
            if "checked_capacity_per_seed" in r
            else ""
        )
        print(
            f"| {r['seeds']} | {r['agent_gib']:.2f} | {r['update_temp_gib']:.2f} "
            f"| {r['max_capacity_per_seed']:,} | {checked} |"
        )
    save_json(
        dict(
            device=device.device_kind,
            jax=jax.__version__,
            limit_gib=limit / GIB,
            entry_bytes=entry,
            args=vars(args),
            rows=rows,
        ),
        args.out,
        f"benchmarks/results/memory_{device.platform}.json",
    )


if __name__ == "__main__":
    main()
