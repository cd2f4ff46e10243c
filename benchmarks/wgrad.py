"""The encoder's stride-1 filter gradients: cuDNN's against dear_jax.wgrad's Pallas kernel.

    python -m benchmarks.wgrad [--seeds 5] [--batch 512] [--iters 20]
        [--images 1 2 4 8] [--warps 2 4 8]

One program computes, for every seed, the filter gradients of the encoder's three stride-1
3x3 convolutions (bf16 inputs [batch, 41|39|37, ..., 32], 32 filters), from per-seed inputs and
output gradients, the way the learner's update does:
- cudnn_loop: cuDNN, once per seed (agent.seed_axis="hybrid", "loop");
- cudnn_vmap: cuDNN under jax.vmap (one batch-grouped convolution per layer: "vmap");
- pallas: the Pallas kernel under jax.vmap (one launch per layer for all seeds), for each
  images-per-program x warps choice.
For each: milliseconds per call (run to the end), the host's dispatch per call, and the largest
difference from cudnn_loop relative to its largest magnitude. Writes JSON.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp

from benchmarks.common import save_json, timed_calls
from dear_jax import wgrad

SIZES = (41, 39, 37)  # the stride-1 layers' input heights and widths at 84x84 frames


def _cudnn(x, g):
    def conv(w):
        return jax.lax.conv_general_dilated(
            x, w, (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC")
        )

    w = jnp.zeros((3, 3, x.shape[-1], g.shape[-1]), x.dtype)
    return jax.vjp(conv, w)[1](g)[0].astype(jnp.float32)


def variants(images: list[int], warps: list[int]) -> dict:
    """name -> function of (xs, gs) (lists over layers of [seeds, batch, ...]) -> gradients."""

    def cudnn_loop(xs, gs):
        return [jnp.stack([_cudnn(x[s], g[s]) for s in range(x.shape[0])]) for x, g in zip(xs, gs)]

    def cudnn_vmap(xs, gs):
        return [jax.vmap(_cudnn)(x, g) for x, g in zip(xs, gs)]

    out = dict(cudnn_loop=cudnn_loop, cudnn_vmap=cudnn_vmap)
    for i in images:
        for w in warps:

            def pallas(xs, gs, i=i, w=w):
                fn = jax.vmap(lambda x, g: wgrad.filter_gradient(x, g, 3, images=i, num_warps=w))
                return [fn(x, g) for x, g in zip(xs, gs)]

            out[f"pallas_images{i}_warps{w}"] = pallas
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--iters", type=int, default=20)
    p.add_argument("--images", type=int, nargs="+", default=[1, 2, 4, 8])
    p.add_argument("--warps", type=int, nargs="+", default=[2, 4, 8])
    p.add_argument("--out", default=None)
    args = p.parse_args()
    keys = iter(jax.random.split(jax.random.key(0), 2 * len(SIZES)))
    shape = (args.seeds, args.batch)
    xs = [jax.random.normal(next(keys), (*shape, n, n, 32), jnp.bfloat16) for n in SIZES]
    gs = [jax.random.normal(next(keys), (*shape, n - 2, n - 2, 32), jnp.bfloat16) for n in SIZES]
    rows, reference = [], None
    for name, fn in variants(args.images, args.warps).items():
        step = jax.jit(fn)
        try:
            result = jax.block_until_ready(step(xs, gs))
        except Exception as e:  # a choice Triton cannot compile is reported, not fatal
            print(f"{name}: {type(e).__name__}: {str(e).splitlines()[0][:200]}")
            rows.append(dict(variant=name, error=str(e)[:500]))
            continue
        if reference is None:
            reference = result
        error = max(
            float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b))) for a, b in zip(result, reference)
        )
        ms, dispatch = timed_calls(lambda _, step=step: step(xs, gs), args.iters)
        rows.append(dict(variant=name, ms_per_call=ms, dispatch_ms_per_call=dispatch, error=error))
    device = jax.devices()[0].device_kind
    print(
        f"{device}, jax {jax.__version__}: filter gradients of {len(SIZES)} layers x "
        f"{args.seeds} seeds, batch {args.batch}, bf16"
    )
    print("| variant | ms per call | host dispatch ms per call | max rel. difference |")
    print("|---|---:|---:|---:|")
    for r in rows:
        if "ms_per_call" in r:
            print(
                f"| {r['variant']} | {r['ms_per_call']:.3f} | {r['dispatch_ms_per_call']:.3f} "
                f"| {r['error']:.1e} |"
            )
        else:
            print(f"| {r['variant']} | failed | | |")
    save_json(
        dict(device=device, jax=jax.__version__, args=vars(args), rows=rows),
        args.out,
        "benchmarks/results/wgrad_gpu.json",
    )


if __name__ == "__main__":
    main()
