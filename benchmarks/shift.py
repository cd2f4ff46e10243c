"""Time DrQ-v2's random shift as the update uses it, for each of `augment.SHIFT_IMPLS`.

    python -m benchmarks.shift --seeds 5 --batch 512 [--iters 20] [--out F.json]

One program shifts, for each of S seeds in turn (as `agent.seed_axis="loop"` does), a batch's
obs and mask by one offset per sample and next_obs by another, keeps the shifted pixels apart
(the optimisation barrier the bf16 conv trunk puts before its input) and converts them to the
encoder's input (bf16 in [-0.5, 0.5]). Each way is checked bit for bit against "pad_slice".
Prints ms per seed-update and writes JSON.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import save_json
from dear_jax import augment
from dear_jax.networks import preprocess

PAD = augment.DEFAULT_PAD


def program(impl: str):
    shift_batch = jax.vmap(lambda image, offset: augment.shift(image, offset, PAD, impl))

    def one_seed(obs, next_obs, mask, off, off_next):
        shifted = shift_batch(obs, off), shift_batch(next_obs, off_next), shift_batch(mask, off)
        obs, next_obs, mask = jax.lax.optimization_barrier(shifted)
        encoder_input = lambda x: preprocess(x).astype(jnp.bfloat16)  # noqa: E731
        return encoder_input(obs), encoder_input(next_obs), mask

    def run(obs, next_obs, mask, off, off_next):
        return [
            one_seed(*(a[s] for a in (obs, next_obs, mask, off, off_next))) for s in range(len(obs))
        ]

    return jax.jit(run)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    s, b = args.seeds, args.batch
    keys = jax.random.split(jax.random.key(0), 5)
    obs = jax.random.randint(keys[0], (s, b, 84, 84, 9), 0, 256).astype(jnp.uint8)
    next_obs = jax.random.randint(keys[1], (s, b, 84, 84, 9), 0, 256).astype(jnp.uint8)
    mask = jax.random.randint(keys[2], (s, b, 84, 84, 3), 0, 2).astype(jnp.uint8)
    off = jax.random.randint(keys[3], (s, b, 2), 0, 2 * PAD + 1)
    off_next = jax.random.randint(keys[4], (s, b, 2), 0, 2 * PAD + 1)
    inputs = (obs, next_obs, mask, off, off_next)
    reference = None
    rows, result = [], {"device": jax.devices()[0].device_kind, "args": vars(args), "ways": {}}
    for impl in augment.SHIFT_IMPLS:
        f = program(impl)
        out = jax.block_until_ready(f(*inputs))
        got = [np.asarray(x.astype(jnp.float32)) for seed in out for x in seed]
        reference = got if reference is None else reference
        same = all(np.array_equal(x, y) for x, y in zip(got, reference))
        times = []
        for _ in range(args.iters):
            t = time.perf_counter()
            jax.block_until_ready(f(*inputs))
            times.append(time.perf_counter() - t)
        ms = 1000 * float(np.median(times)) / s
        result["ways"][impl] = {"ms_per_seed": ms, "same_as_pad_slice": same}
        rows.append(f"| {impl} | {ms:.3f} | {'yes' if same else 'NO'} |")
    result["fastest"] = min(result["ways"], key=lambda k: result["ways"][k]["ms_per_seed"])
    print(
        f"{result['device']}, {s} seeds x batch {b}: obs + next_obs + mask, shifted and converted"
    )
    print("| agent.shift_impl | ms per seed | same pixels |\n| --- | ---: | --- |")
    print("\n".join(rows))
    save_json(result, args.out)
    return result


if __name__ == "__main__":
    main()
