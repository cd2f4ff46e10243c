"""How fast the replay gathers a batch's frame stacks, by the way the gather is written.

    python -m benchmarks.stack_gather --seeds 5 --envs 16 --capacity 100000 --batch 512 --out X.json

A sampled transition's observation is K stored frames [H, W, C] (uint8) laid out as one image
[H, W, K * C], the frames' bytes interleaved pixel by pixel (`replay._gather_stack`). In the
training loop XLA fuses the gather with that interleaving into one kernel that took 0.52 ms of
a 5-seed DEAR update on an H200 (benchmarks/RESULTS.md). This times `replay.sample` over
`--seeds` vmapped replays (filled, every entry sampleable), `--iters` samples in one program,
with each way of writing the gather (`VARIANTS`), checks each against the current one, and
also times the frames gathered without the interleaving ("frames first", [B, K, H, W, C]: what
the gather alone costs). Writes JSON. On an H200 (commit 5811e91) the interleaving cost a
5-seed sample ~0.06 of its 0.36 ms.
"""

from __future__ import annotations

import argparse
import functools

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import save_json, timed_calls
from dear_jax import replay


def _frames(buf, rows, env):
    return buf[rows, env[:, None]]  # [B, K, H, W, (C)]


def _interleave(x):
    if x.ndim == 4:
        x = x[..., None]
    b, k, h, w, c = x.shape
    return jnp.moveaxis(x, 1, 3).reshape(b, h, w, k * c)


def _apart(buf, rows, env):
    """The frames gathered and written out whole, then interleaved by a kernel of its own."""
    return _interleave(jax.lax.optimization_barrier(_frames(buf, rows, env)))


def _concatenated(buf, rows, env):
    """Each frame of the stack gathered alone, the stack their concatenation along channels."""
    frames = [buf[rows[:, k], env] for k in range(rows.shape[1])]
    frames = [f[..., None] if f.ndim == 3 else f for f in frames]
    return jnp.concatenate(frames, axis=-1)


def _frames_first(buf, rows, env):
    return _frames(buf, rows, env)


VARIANTS = {
    "current": replay._gather_stack,
    "apart": _apart,
    "concatenated": _concatenated,
    "frames first (no interleaving)": _frames_first,
}


def filled_replay(seeds: int, envs: int, capacity: int, frame_shape) -> replay.ReplayState:
    """Replays whose every row is written, each frame's bytes a pattern of its pixel and
    channel plus a value of its (seed, row, env)."""
    state = replay.init(capacity, envs, frame_shape, 6, leading=(seeds,))
    rows = state.frames.shape[1]
    fill = np.arange(seeds * rows * envs, dtype=np.uint32) * np.uint32(2654435761) >> 24
    fill = jnp.asarray(fill.astype(np.uint8).reshape(seeds, rows, envs, 1, 1, 1))
    h, w, c = frame_shape
    pattern = jnp.arange(h * w * c, dtype=jnp.uint8).reshape(1, 1, 1, h, w, c)
    return state.replace(
        frames=fill + pattern,
        masks=jnp.broadcast_to(fill[..., 0] & 1, state.masks.shape),
        episode=jnp.zeros_like(state.episode),
        episodes_started=jnp.ones_like(state.episodes_started),
        pos=jnp.zeros_like(state.pos),
        size=jnp.full_like(state.size, rows),
    )


def _repeated(sample, state, keys):
    """`sample` at each of keys' first axis in one program (each batch written out whole:
    `replay.sample_at`'s barrier), so that the GPU's time, not the launch, is what is timed."""

    def body(total, key):
        batch = sample(state, key)
        return total + batch.obs[..., 0, 0, 0].astype(jnp.int32).sum(), None

    return jax.lax.scan(body, jnp.int32(0), keys)[0]


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--envs", type=int, default=16)
    parser.add_argument("--capacity", type=int, default=100_000)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--nstep", type=int, default=3)
    parser.add_argument("--iters", type=int, default=20, help="samples per program")
    parser.add_argument("--calls", type=int, default=5, help="programs timed")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    state = filled_replay(args.seeds, args.envs, args.capacity, (84, 84, 3))
    keys = jax.random.split(jax.random.key(0), (args.iters, args.seeds))
    rows, reference = [], None
    for name, gather in VARIANTS.items():
        replay._gather_stack = gather
        try:
            sample = functools.partial(
                replay.sample, batch_size=args.batch, nstep=args.nstep, gamma=0.99, frame_stack=3
            )
            batch = jax.block_until_ready(jax.jit(jax.vmap(sample))(state, keys[0]))
            fn = jax.jit(functools.partial(_repeated, jax.vmap(sample)))
            jax.block_until_ready(fn(state, keys))
            ms, dispatch = timed_calls(lambda i, fn=fn: fn(state, keys), args.calls)
            ms, dispatch = ms / args.iters, dispatch / args.iters
        finally:
            replay._gather_stack = VARIANTS["current"]
        if reference is None:
            reference = batch
        elif batch.obs.shape == reference.obs.shape:
            for a, b in zip(jax.tree.leaves(batch), jax.tree.leaves(reference), strict=True):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        rows.append(dict(variant=name, ms_per_sample=ms, dispatch_ms_per_sample=dispatch))
        print(f"{name}: {ms:.3f} ms per sample of {args.seeds} seeds (dispatch {dispatch:.3f})")
    result = dict(args=vars(args), device=jax.devices()[0].device_kind, rows=rows)
    save_json(result, args.out)
    return result


if __name__ == "__main__":
    main()
