"""The encoder's input path on the GPU: random shift, uint8 -> float, the 9-channel first conv.

    python -m benchmarks.encoder_input [--batch 512] [--dtypes bfloat16 float32]

The first convolution sees 9 channels (3 stacked RGB frames), not a multiple of 8, so cuDNN has
no tensor-core kernel for it. Each variant below computes the same function: the conv trunk
(4 convs + ReLU) on shifted obs with gradient and on shifted next_obs without, as the update
does; only how the pixels reach the first convolution differs:
  plain          shift (uint8) -> float -> conv1 on 9 channels
  pad            shift -> float -> zero channels to 16 -> conv1 (16 channels)
  pad_uint8      zero channels to 16 on uint8 first (kept apart by a barrier) -> shift -> float
  shift_apart    shift, a barrier, then float + zero channels to 16
  space_to_depth shift -> float -> 2x2 blocks to channels (42 x 42 x 36, padded to 40) -> a 2x2
                 stride-1 convolution with the 3x3 stride-2 kernel rearranged (zeros elsewhere)
Prints ms per call (forward + backward of obs, forward of next_obs) and writes JSON.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

from benchmarks.common import save_json
from dear_jax import augment
from dear_jax.networks import _conv2d, _pad_axis, preprocess

VARIANTS = ("plain", "pad", "pad_uint8", "shift_apart", "space_to_depth")


def _space_to_depth_conv(x, w):
    """The 3x3 stride-2 VALID conv of x [B, 84, 84, C] as a 2x2 stride-1 conv on 2x2 blocks."""
    b, h, wd, c = x.shape
    blocks = x.reshape(b, h // 2, 2, wd // 2, 2, c).transpose(0, 1, 3, 2, 4, 5)
    blocks = blocks.reshape(b, h // 2, wd // 2, 4 * c)
    w4 = jnp.zeros((4, 4, c, w.shape[-1]), w.dtype).at[:3, :3].set(w)  # taps 3 are zero
    w2 = w4.reshape(2, 2, 2, 2, c, -1).transpose(0, 2, 1, 3, 4, 5).reshape(2, 2, 4 * c, -1)
    return _conv2d(blocks, w2, 1, x.dtype, 8)  # 36 channels padded to 40


def first_layer_input(obs, key, variant, dtype):
    if variant == "pad_uint8":
        obs = jax.lax.optimization_barrier(_pad_axis(obs, -1, 8))
    x = augment.random_shift_batch(obs, key)
    if variant == "shift_apart":
        x = jax.lax.optimization_barrier(x)
    x = preprocess(x).astype(dtype)
    if variant in ("pad", "shift_apart"):
        x = _pad_axis(x, -1, 8)
    return x


def trunk(params, obs, key, variant, dtype):
    x = first_layer_input(obs, key, variant, dtype)
    w1 = params[0][0]
    if variant == "space_to_depth":
        y = _space_to_depth_conv(x, w1.astype(dtype))
    else:
        # The kernel's input channels are zero-padded to match padded pixels (16), if any.
        y = _conv2d(x, w1, 2, dtype, 8 if x.shape[-1] != w1.shape[2] else 1)
    x = jax.nn.relu(y + params[0][1].astype(dtype))
    for w, b in params[1:]:
        x = jax.nn.relu(_conv2d(x, w, 1, dtype, 1) + b.astype(dtype))
    return x


def make_step(variant, dtype):
    def loss(params, obs, next_obs, key):
        k1, k2 = jax.random.split(key)
        y = trunk(params, obs, k1, variant, dtype)
        y_next = jax.lax.stop_gradient(trunk(params, next_obs, k2, variant, dtype))
        return jnp.mean(y.astype(jnp.float32)) + jnp.mean(y_next.astype(jnp.float32))

    return jax.jit(jax.grad(loss))


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--dtypes", nargs="+", default=["bfloat16"])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    k = jax.random.split(jax.random.key(0), 6)
    shapes = [(3, 3, 9, 32)] + [(3, 3, 32, 32)] * 3
    params = [(0.1 * jax.random.normal(kk, s), jnp.zeros(32)) for kk, s in zip(k, shapes)]
    obs, next_obs = (
        jax.random.randint(kk, (args.batch, 84, 84, 9), 0, 256).astype(jnp.uint8) for kk in k[4:]
    )
    rows, reference = [], None
    for dtype in args.dtypes:
        for variant in args.variants:
            step = make_step(variant, jnp.dtype(dtype))
            grads = step(params, obs, next_obs, jax.random.key(1))
            jax.block_until_ready(grads)
            if reference is None or reference[0] != dtype:
                reference = (dtype, grads)
            err = max(
                float(jnp.max(jnp.abs(a - b)) / (jnp.max(jnp.abs(b)) + 1e-12))
                for a, b in zip(jax.tree.leaves(grads), jax.tree.leaves(reference[1]))
            )
            t0 = time.perf_counter()
            for i in range(args.iters):
                grads = step(params, obs, next_obs, jax.random.key(i))
            jax.block_until_ready(grads)
            ms = (time.perf_counter() - t0) / args.iters * 1e3
            rows.append(dict(variant=variant, dtype=dtype, ms=ms, rel_grad_diff_vs_first=err))
            print(f"{variant} {dtype}: {ms:.3f} ms (grads vs the first variant: {err:.1e})")
    device = jax.devices()[0].device_kind
    print(f"\nbatch {args.batch}, {device}\n| variant | dtype | ms per call |\n|---|---|---:|")
    for r in rows:
        print(f"| {r['variant']} | {r['dtype']} | {r['ms']:.3f} |")
    save_json(
        dict(device=device, jax=jax.__version__, args=vars(args), rows=rows),
        args.out,
        f"benchmarks/results/encoder_input_{jax.devices()[0].platform}.json",
    )


if __name__ == "__main__":
    main()
