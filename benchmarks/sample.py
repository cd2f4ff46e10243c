"""Time drawing a batch from the replay as the trainer's learn program does (all seeds at once).

    python -m benchmarks.sample --seeds 5 --envs 16 --capacity 100000 --batch 512 [--profile]

The replay is full (episodes of 501 entries, as walker's) and of the loop's shape, [S, T, E, ...].
Rows: the whole `replay.sample` (vmapped over seeds), its two halves timed alone (the draw of
indices: valid-start weights, running count and search; the gathers of `replay.sample_at` at
fixed indices), and the sample as it was before `replay.sample_at`'s two optimisation barriers
(rows before the image gathers, the batch written out whole) were added. The second barrier
matters only where the batch is consumed in the same program (the learn program's random shift):
`benchmarks/profile_loop.py` measures that. With --profile, the GPU kernels of the whole sample
are listed. Writes JSON.
"""

from __future__ import annotations

import argparse
import collections
import tempfile
import time
from unittest import mock

import jax
import jax.numpy as jnp

from benchmarks.common import save_json
from benchmarks.profile_update import device_events, hlo_op_names
from dear_jax import replay

EPISODE_ENTRIES = 501  # a 1000-frame episode at action repeat 2, and its first frame


def full_replay(seeds: int, envs: int, capacity: int, action_dim: int = 6):
    """A wrapped-around replay: every row written, episodes of EPISODE_ENTRIES rows."""
    buf = replay.init(capacity, envs, (84, 84, 3), action_dim, leading=(seeds,))
    rows = buf.frames.shape[1]
    pos = rows // 3  # the next row to write: the oldest stored one
    age = (jnp.arange(rows, dtype=jnp.int32) - pos) % rows
    episode = (age // EPISODE_ENTRIES)[:, None]  # ids grow with age, as the ring writes them
    return buf.replace(
        episode=jnp.broadcast_to(episode, (seeds, rows, envs)),
        pos=jnp.full((seeds,), pos, jnp.int32),
        size=jnp.full((seeds,), rows, jnp.int32),
    )


def programs(batch: int, nstep: int, frame_stack: int, same_episode: bool):
    kw = dict(nstep=nstep, gamma=0.99, frame_stack=frame_stack)

    def draw(buf, key):
        weights = replay.sample_weights(buf, frame_stack).reshape(-1)
        return jnp.divmod(replay._draw(key, weights, batch), buf.frames.shape[1])

    def at(buf, row, env, key):
        return replay.sample_at(buf, row, env, far_key=key if same_episode else None, **kw)

    def whole(buf, key):
        return replay.sample(buf, key, batch, same_episode=same_episode, **kw)

    def fused(buf, key):  # both barriers of replay.sample_at taken out
        with mock.patch.object(jax.lax, "optimization_barrier", lambda x: x):
            return whole(buf, key)

    return {
        "sample": jax.jit(jax.vmap(whole)),
        "sample, index arithmetic fused into the gathers (before)": jax.jit(jax.vmap(fused)),
        "draw": jax.jit(jax.vmap(draw)),
        "gather at fixed indices": jax.jit(jax.vmap(at)),
    }


def time_ms(fn, args_of, iters: int) -> float:
    jax.block_until_ready(fn(*args_of(0)))
    calls = [args_of(i + 1) for i in range(iters)]  # keys made before the clock starts
    jax.block_until_ready(calls)
    t0 = time.perf_counter()
    for args in calls:
        out = fn(*args)
    jax.block_until_ready(out)
    return (time.perf_counter() - t0) / iters * 1e3


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--envs", type=int, default=16)
    parser.add_argument("--capacity", type=int, default=100_000, help="entries per seed")
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--nstep", type=int, default=1)
    parser.add_argument("--frame-stack", type=int, default=3)
    parser.add_argument("--ted", action="store_true", help="also draw TED's same-episode frames")
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--profile", action="store_true", help="list the GPU kernels of a sample")
    parser.add_argument("--top", type=int, default=15)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    buf = full_replay(args.seeds, args.envs, args.capacity)
    progs = programs(args.batch, args.nstep, args.frame_stack, args.ted)
    keys = lambda i: jax.random.split(jax.random.key(i), args.seeds)  # noqa: E731
    draw = progs["draw"]
    row, env = draw(buf, keys(0))
    args_of = {
        "draw": lambda i: (buf, keys(i)),
        "gather at fixed indices": lambda i: (buf, row, env, keys(i)),
    }
    rows = []
    for name, fn in progs.items():
        # Each program is timed twice, the second time reported: the first pass over the buffer
        # also pays for warming up whatever the device does on first touch.
        for _ in range(2):
            ms = time_ms(fn, args_of.get(name, lambda i: (buf, keys(i))), args.iters)
        rows.append(dict(program=name, ms_per_call=ms, ms_per_seed=ms / args.seeds))
    device = jax.devices()[0]
    print(
        f"{device.device_kind}: {args.seeds} seeds x {buf.frames.shape[1]} rows x {args.envs} envs, "
        f"batch {args.batch}, nstep {args.nstep}, jax {jax.__version__}"
    )
    print("| program | ms per call | ms per seed |\n|---|---:|---:|")
    for r in rows:
        print(f"| {r['program']} | {r['ms_per_call']:.3f} | {r['ms_per_seed']:.3f} |")

    kernels = {}
    if args.profile:
        fn = progs["sample"]
        names = hlo_op_names(fn.lower(buf, keys(0)).compile().as_text())
        trace_dir = tempfile.mkdtemp(prefix="dear_jax_sample_")
        jax.profiler.start_trace(trace_dir)
        for i in range(args.iters):
            out = fn(buf, keys(i))
        jax.block_until_ready(out)
        jax.profiler.stop_trace()
        per_kernel = collections.Counter()
        for kernel, hlo_op, ns in device_events(trace_dir):
            per_kernel[f"{hlo_op or '?'} | {kernel[:50]} | {names.get(hlo_op, '')[-60:]}"] += ns
        kernels = {k: ns * 1e-6 / args.iters for k, ns in per_kernel.most_common(args.top)}
        print(
            "\n| kernel of a whole sample (hlo op / kernel / op name) | ms per call |\n|---|---:|"
        )
        for k, ms in kernels.items():
            print(f"| {k} | {ms:.3f} |")
    save_json(
        dict(
            device=device.device_kind,
            jax=jax.__version__,
            args=vars(args),
            rows=rows,
            kernels=kernels,
        ),
        args.out,
        f"benchmarks/results/sample_{device.platform}.json",
    )


if __name__ == "__main__":
    main()
