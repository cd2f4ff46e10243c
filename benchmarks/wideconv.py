"""The stride-1 conv stacks of a DEAR update: cuDNN layer by layer against dear_jax.wideconv.

    python -m benchmarks.wideconv [--seeds 5] [--batch 512] [--iters 20]
        [--widths 4 1] [--blocks 64 128] [--warps 4 8]

For every seed (vmapped, as the update does), bf16:
- encoder: relu(conv 3x3) x 3 on [batch, 41, 41, 32] -> [batch, 35, 35, 32];
- decoder: relu(transposed conv 3x3, stride 1) x 3 on [batch, 35, 35, 16] -> [batch, 41, 41, 32].
Each as a forward pass alone (as for next_obs) and as forward + backward (input and parameter
gradients of a sum of the outputs), by:
- xla_loop: each convolution once per seed on cuDNN (agent.seed_axis="hybrid", the default);
- pallas: `wideconv.conv_stack`, for each pixels-per-load x rows-per-block x warps choice.
Prints ms per call, the host's dispatch per call, and the largest difference from the same pass
in float32 (cuDNN, all seeds at once; per output, relative to its largest magnitude); writes JSON. Sets wideconv's defaults to nothing: the
fastest choice is for the reader to write into dear_jax/wideconv.py.
"""

from __future__ import annotations

import argparse
import itertools

import jax
import jax.numpy as jnp

from benchmarks.common import save_json, timed_calls
from dear_jax import networks, wideconv

STACKS = dict(encoder=(41, (32, 32, 32, 32), 0), decoder=(35, (16, 32, 32, 32), 2))


def _xla_stack(x, layers, pad):
    for k, b in layers:
        x = jnp.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
        x = jax.nn.relu(networks._conv2d(x, k, 1, x.dtype, 8) + b.astype(x.dtype))
    return x


def _programs(impl, pad):
    def stack(x, layers):
        if impl == "pallas":
            return wideconv.conv_stack(x, layers, pad)
        if impl == "float32":
            return _xla_stack(x.astype(jnp.float32), layers, pad)
        with networks.conv_settings(loop_seeds=True):
            return _xla_stack(x, layers, pad)

    def loss(x, layers):
        return jnp.sum(stack(x, layers).astype(jnp.float32))

    forward = jax.jit(jax.vmap(stack))
    both = jax.jit(jax.vmap(jax.value_and_grad(loss, (0, 1))))
    return dict(forward=forward, forward_backward=both)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--iters", type=int, default=20)
    p.add_argument("--widths", type=int, nargs="+", default=[4, 1], choices=[1, 4])
    p.add_argument("--blocks", type=int, nargs="+", default=[64, 128])
    p.add_argument("--warps", type=int, nargs="+", default=[4, 8])
    p.add_argument("--out", default=None)
    args = p.parse_args()
    rows = []
    for name, (size, channels, pad) in STACKS.items():
        keys = iter(jax.random.split(jax.random.key(0), 8))
        x = jax.random.normal(next(keys), (args.seeds, args.batch, size, size, channels[0]))
        x = jax.nn.relu(x).astype(jnp.bfloat16)
        layers = tuple(
            (
                jax.random.normal(next(keys), (args.seeds, 3, 3, c, f)) * (2 / (9 * c)) ** 0.5,
                jnp.zeros((args.seeds, f)),
            )
            for c, f in zip(channels, channels[1:])
        )
        choices = [("xla_loop", None)] + [
            ("pallas", c) for c in itertools.product(args.widths, args.blocks, args.warps)
        ]
        reference = {
            k: [a.astype(jnp.float32) for a in jax.tree.leaves(fn(x, layers))]
            for k, fn in _programs("float32", pad).items()
        }
        for impl, choice in choices:
            variant = impl
            if choice:
                wideconv.WIDTH, wideconv.BLOCK, wideconv.NUM_WARPS = choice
                variant = "pallas_width{}_block{}_warps{}".format(*choice)
            for pass_name, fn in _programs(impl, pad).items():
                try:
                    out = jax.block_until_ready(fn(x, layers))
                except Exception as e:  # a choice Triton cannot compile is reported, not fatal
                    print(f"{name} {variant} {pass_name}: {type(e).__name__}: {str(e)[:300]}")
                    rows.append(
                        dict(stack=name, variant=variant, pass_=pass_name, error=str(e)[:500])
                    )
                    continue
                flat = [a.astype(jnp.float32) for a in jax.tree.leaves(out)]
                ref = reference[pass_name]
                error = max(
                    float(jnp.max(jnp.abs(a - b)) / (jnp.max(jnp.abs(b)) + 1e-30))
                    for a, b in zip(flat, ref)
                )
                ms, dispatch = timed_calls(lambda _, fn=fn, x=x, ws=layers: fn(x, ws), args.iters)
                rows.append(
                    dict(
                        stack=name,
                        variant=variant,
                        pass_=pass_name,
                        ms_per_call=ms,
                        ms_per_seed=ms / args.seeds,
                        dispatch_ms_per_call=dispatch,
                        error=error,
                    )
                )
                print(f"{name} {variant} {pass_name}: {ms:.3f} ms/call, error {error:.1e}")
    device = jax.devices()[0].device_kind
    print(f"{device}, jax {jax.__version__}: {args.seeds} seeds, batch {args.batch}, bf16")
    print(
        "| stack | variant | pass | ms per call | ms per seed | host dispatch ms | max rel. diff |"
    )
    print("|---|---|---|---:|---:|---:|---:|")
    for r in rows:
        if "ms_per_call" in r:
            print(
                f"| {r['stack']} | {r['variant']} | {r['pass_']} | {r['ms_per_call']:.3f} | "
                f"{r['ms_per_seed']:.3f} | {r['dispatch_ms_per_call']:.3f} | {r['error']:.1e} |"
            )
        else:
            print(f"| {r['stack']} | {r['variant']} | {r['pass_']} | failed | | | |")
    save_json(
        dict(device=device, jax=jax.__version__, args=vars(args), rows=rows),
        args.out,
        "benchmarks/results/wideconv_gpu.json",
    )


if __name__ == "__main__":
    main()
