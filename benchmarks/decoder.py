"""The decoder's transposed convolutions: phase form (networks.ConvTranspose) against
lax.conv_transpose, forward + backward (gradients of input, kernel and bias).

python -m benchmarks.decoder [--batch 512] [--iters 20]
Prints a table (ms per forward+backward) and writes JSON to benchmarks/results/decoder_<platform>.json.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

from benchmarks.common import save_json
from dear_jax import networks

# (kernel, stride, output padding, in channels, out channels, input size): the mask decoder's layers.
LAYERS = ((4, 4, 3, 16, 16, 8), (3, 1, 0, 16, 32, 35), (3, 1, 0, 32, 32, 37), (3, 2, 1, 32, 3, 41))


def lax_form(k, s, op):
    pad = (k - 1, k - 1 + op)

    def apply(p, x):
        y = jax.lax.conv_transpose(
            x, p["kernel"], (s, s), (pad, pad), dimension_numbers=("NHWC", "HWIO", "NHWC")
        )
        return y + p["bias"]

    return apply


def time_grad(apply, params, x, iters):
    f = jax.jit(jax.grad(lambda p, x: jnp.sum(apply(p, x) ** 2), argnums=(0, 1)))
    jax.block_until_ready(f(params, x))
    t0 = time.perf_counter()
    for _ in range(iters):
        out = f(params, x)
    jax.block_until_ready(out)
    return (time.perf_counter() - t0) / iters * 1e3


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    rows = []
    for k, s, op, cin, cout, n in LAYERS:
        x = jax.random.normal(jax.random.key(0), (args.batch, n, n, cin))
        layer = networks.ConvTranspose(cout, k, s, op)
        params = layer.init(jax.random.key(1), x)["params"]
        phase = time_grad(lambda p, x, m=layer: m.apply({"params": p}, x), params, x, args.iters)
        dilated = time_grad(lax_form(k, s, op), params, x, args.iters)
        rows.append(
            dict(layer=f"{cin}->{cout}, {k}x{k}/{s}, {n}px", phase_ms=phase, lax_ms=dilated)
        )
        print(rows[-1])
    device = jax.devices()[0]
    print(f"\nbatch {args.batch}, {device.device_kind}, jax {jax.__version__}")
    print("| layer | phase form ms | lax.conv_transpose ms |\n|---|---:|---:|")
    for r in rows:
        print(f"| {r['layer']} | {r['phase_ms']:.2f} | {r['lax_ms']:.2f} |")
    save_json(
        dict(device=device.device_kind, batch=args.batch, rows=rows),
        args.out,
        f"benchmarks/results/decoder_{device.platform}.json",
    )


if __name__ == "__main__":
    main()
