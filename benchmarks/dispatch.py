"""What launching one op costs the host, per kind of op, against what it costs the GPU.

    python -m benchmarks.dispatch [--ops 48] [--iters 20] [--batch 512]

The learner's update on an H100 takes about as long to launch as to run
(benchmarks/RESULTS.md, "the host's launches"), so the host's cost per op sets a floor. Each
program here is a chain of --ops ops of one kind at the encoder's shapes (bf16 activations
[batch, 41, 41, 32], 3x3 kernels), kept apart by optimisation barriers so that XLA cannot fuse
them: element-wise fusions, small element-wise fusions (one float per op), convolutions, and
convolutions with their filter gradient (cuDNN's, or dear_jax.wgrad's Pallas kernel:
conv_wgrad_pallas) or input gradient. For each: milliseconds per call (run to the
end), the host's dispatch (the time the calls take to return) and both per op. Writes JSON.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp

from benchmarks.common import save_json, timed_calls
from dear_jax import wgrad


def _conv(x, w):
    return jax.lax.conv_general_dilated(
        x, w, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
    )


def _barrier(x):
    return jax.lax.optimization_barrier(x)


def chains(ops: int):
    """name -> (function of (x, w, g), ops of its kind per call)."""

    def fusion(x, w, g):
        for _ in range(ops):
            x = _barrier(jnp.maximum(x * 1.001, 0.0))
        return x

    def small(x, w, g):
        s = jnp.sum(w)
        for _ in range(ops):
            s = _barrier(s * 1.001 + 1.0)
        return s

    def conv(x, w, g):
        for _ in range(ops):
            x = _barrier(jax.nn.relu(_conv(x, w)))
        return x

    def conv_wgrad(x, w, g):
        grads = []
        for _ in range(ops):
            grads.append(jax.vjp(_conv, x, w)[1](g)[1])
            x = _barrier(jax.nn.relu(_conv(x, w)))
        return x, grads

    def conv_dgrad(x, w, g):
        grads = []
        for _ in range(ops):
            grads.append(jax.vjp(lambda x: _conv(x, w), x)[1](g)[0])
            x = _barrier(jax.nn.relu(_conv(x, w)))
        return x, grads

    def conv_wgrad_pallas(x, w, g):
        grads = []
        for _ in range(ops):
            # VALID, as the Pallas kernel computes it: the gradient of the interior output.
            grads.append(wgrad.filter_gradient(x, g[:, 1:-1, 1:-1], 3))
            x = _barrier(jax.nn.relu(_conv(x, w)))
        return x, grads

    return dict(
        fusion=fusion,
        small_fusion=small,
        conv=conv,
        conv_wgrad=conv_wgrad,
        conv_wgrad_pallas=conv_wgrad_pallas,
        conv_dgrad=conv_dgrad,
    )


def time_chain(fn, args, iters: int) -> tuple[float, float]:
    """(ms per call, host dispatch ms per call) of jit(fn) after one compiling call."""
    step = jax.jit(fn)
    jax.block_until_ready(step(*args))
    return timed_calls(lambda _: step(*args), iters)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--ops", type=int, default=48)
    p.add_argument("--iters", type=int, default=20)
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    k = jax.random.split(jax.random.key(0), 3)
    shape = (args.batch, 41, 41, 32)
    x = jax.random.normal(k[0], shape, jnp.bfloat16)
    w = (jax.random.normal(k[1], (3, 3, 32, 32)) * 0.08).astype(jnp.bfloat16)
    g = jax.random.normal(k[2], shape, jnp.bfloat16)
    rows = []
    for name, fn in chains(args.ops).items():
        ms, dispatch = time_chain(fn, (x, w, g), args.iters)
        rows.append(dict(kind=name, ops=args.ops, ms_per_call=ms, dispatch_ms_per_call=dispatch))
    # The gradient chains also run the forward chain: their own op is the difference.
    base = {r["kind"]: r for r in rows}["conv"]
    for r in rows:
        minus = base if r["kind"].startswith("conv_") else None
        r["us_per_op"] = (
            (r["ms_per_call"] - (minus["ms_per_call"] if minus else 0)) / r["ops"] * 1e3
        )
        r["dispatch_us_per_op"] = (
            (r["dispatch_ms_per_call"] - (minus["dispatch_ms_per_call"] if minus else 0))
            / r["ops"]
            * 1e3
        )
    device = jax.devices()[0].device_kind
    print(f"{device}, jax {jax.__version__}, {args.ops} ops per program, activations {shape} bf16")
    print("| op | ms per call | host dispatch ms per call | us per op | host us per op |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['kind']} | {r['ms_per_call']:.2f} | {r['dispatch_ms_per_call']:.2f} "
            f"| {r['us_per_op']:.1f} | {r['dispatch_us_per_op']:.1f} |"
        )
    save_json(
        dict(device=device, jax=jax.__version__, args=vars(args), rows=rows),
        args.out,
        "benchmarks/results/dispatch_gpu.json",
    )


if __name__ == "__main__":
    main()
