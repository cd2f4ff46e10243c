"""A 3 x 3 convolution as a Mosaic GPU (Hopper) kernel, against the Pallas (Triton) stack's.

    python -m benchmarks.conv_mgpu --batch 512 --side 39 --blocks 64 128 --iters 200 --out X.json

The question: would the conv stacks gain from a block's input held in shared memory? The Triton
kernels (`dear_jax/wideconv.py`) read each of a block's 9 taps from memory through L1 (Nsight
Compute: L1 at 61-80% of its peak). Here a layer's activations sit on a grid whose rows are a
multiple of 8 pixels wide (`--width`, >= the input's side), so that tap (i, j) is the input
shifted by i * width + j rows, and a block's products are warpgroup MMAs (`conv_mgpu`). The
price: the grid's extra columns and rows are computed too (a 37 x 37 output on a 39 x 40 grid:
14% more rows).

It times, for `--batch` images of `--side` x `--side` x 32 channels (a lone seed's encoder layer
at batch 512: 39 -> 37), the bf16 forward with ReLU: this kernel per `--blocks` (rows per
program), the Triton stack's kernel (`wideconv.conv_stack`, one VALID layer), and XLA's (cuDNN);
it checks the kernel's valid outputs against XLA's (`--parts`: each way of reading the taps
apart, on the taps' weights alone). Each figure is a mean over `--iters` calls from Python,
with the host's time to launch them beside it. Writes JSON. Needs a Hopper GPU.
"""

from __future__ import annotations

import argparse
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import mosaic_gpu as plgpu

from benchmarks.common import save_json, timed_calls

K = 3  # taps per side


def grid_rows(images: int, side: int, width: int) -> int:
    return images * side * width


def to_grid(x: jax.Array, width: int, block: int) -> jax.Array:
    """[N, H, H, C] -> [rows, C]: pixel (y, x) of image n at row (n * H + y) * width + x, zeros
    in the columns past H, then zero rows up to a multiple of `block` plus the halo (2 grid rows
    and 2 pixels, rounded up to 8) that the last block's taps read."""
    n, h, _, c = x.shape
    x = jnp.pad(x, ((0, 0), (0, 0), (0, width - h), (0, 0))).reshape(-1, c)
    rows = -(-x.shape[0] // block) * block
    return jnp.pad(x, ((0, rows - x.shape[0] + halo(width)), (0, 0)))


def halo(width: int) -> int:
    return (K - 1) * width + 8


def from_grid(out: jax.Array, images: int, side: int, width: int, valid: int) -> jax.Array:
    """[rows, F] on the input's grid -> [N, valid, valid, F], the VALID outputs."""
    f = out.shape[-1]
    out = out[: grid_rows(images, side, width)].reshape(images, side, width, f)
    return out[:, :valid, :valid]


def conv_mgpu(
    xg: jax.Array,
    w: jax.Array,
    *,
    width: int,
    block: int,
    tiled_taps: bool = True,
):
    """relu(sum_{i,j} x[q + i * width + j] @ w[i, j]) for every row q of the grid (`to_grid`;
    its last `halo(width)` rows are only read), bf16 out.

    A block's window of input rows (the block and its halo) is copied into shared memory by the
    TMA, tiled and swizzled for the MMAs; the taps j = 0 are its slices at i * width rows (a
    multiple of 8). A tiled copy must start at a multiple of 8 rows, so the taps j = 1, 2 read
    plain copies of the window shifted by j rows, each slice into registers (the MMA's left
    operand may be registers; read at row offset 1 every other output row came out wrong on jax
    0.11.2, at multiples of 8 right: `--parts`). Without `tiled_taps` every tap is read so.
    (The plain copies' buffer keeps a slot for j = 0 either way: a sixth of the shared memory a
    program holds, as measured.)"""
    rows = xg.shape[0] - halo(width)
    c, f = w.shape[2:]
    span = block + halo(width)  # the window's rows
    tiled = lambda n: (  # noqa: E731  (n channels of bf16)
        plgpu.TilingTransform((8, plgpu.find_swizzle(n * 16) // 2)),
        plgpu.SwizzleTransform(plgpu.find_swizzle(n * 16)),
    )
    taps = w.reshape(K * K, c, f)

    plain = range(1 if tiled_taps else 0, K)  # the taps' j read into registers

    def body(x_gmem, w_gmem, o_gmem, x_smem, u_smem, w_smem, o_smem, bars):
        q0 = jax.lax.axis_index("rows") * block
        plgpu.copy_gmem_to_smem(w_gmem, w_smem, bars.at[K])
        if tiled_taps:
            plgpu.copy_gmem_to_smem(x_gmem.at[pl.ds(q0, span)], x_smem, bars.at[0])
        for j in plain:  # a plain copy may start at any row
            plgpu.copy_gmem_to_smem(x_gmem.at[pl.ds(q0 + j, span)], u_smem.at[j], bars.at[j])
        plgpu.barrier_wait(bars.at[K])

        def products(acc_ref):
            if tiled_taps:
                plgpu.barrier_wait(bars.at[0])
                for i in range(K):
                    plgpu.wgmma(acc_ref, x_smem.at[pl.ds(i * width, block)], w_smem.at[i * K])
            for j in plain:
                plgpu.barrier_wait(bars.at[j])
                for i in range(K):
                    a = plgpu.load(
                        u_smem.at[j, pl.ds(i * width, block)],
                        (slice(None), slice(None)),
                        layout=plgpu.Layout.WGMMA,
                        optimized=False,
                    )
                    plgpu.wgmma(acc_ref, a, w_smem.at[i * K + j])
            plgpu.wgmma_wait(0)
            return acc_ref[...]

        acc = pl.run_scoped(products, plgpu.ACC((block, f), jnp.float32))
        o_smem[...] = jnp.maximum(acc, 0.0).astype(o_smem.dtype)
        plgpu.commit_smem()
        plgpu.copy_smem_to_gmem(o_smem, o_gmem.at[pl.ds(q0, block)])
        plgpu.wait_smem_to_gmem(0)

    kernel = plgpu.kernel(
        body,
        out_type=jax.ShapeDtypeStruct((rows, f), xg.dtype),
        grid=(rows // block,),
        grid_names=("rows",),
        scratch_types=(
            plgpu.SMEM((span, c), xg.dtype, transforms=tiled(c)),
            plgpu.SMEM((K, span, c), xg.dtype),
            plgpu.SMEM((K * K, c, f), xg.dtype, transforms=tiled(f)),
            plgpu.SMEM((block, f), xg.dtype, transforms=tiled(f)),
            plgpu.Barrier(num_barriers=K + 1),
        ),
    )
    return kernel(xg, taps)


def xla_conv(x, w):
    out = jax.lax.conv_general_dilated(
        x, w, (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC")
    )
    return jax.nn.relu(out.astype(jnp.float32)).astype(x.dtype)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--side", type=int, default=39, help="the input's side")
    parser.add_argument("--channels", type=int, default=32)
    parser.add_argument(
        "--width", type=int, default=0, help="grid row width; 0: side rounded up to 8"
    )
    parser.add_argument("--blocks", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--iters", type=int, default=50)
    parser.add_argument("--parts", action="store_true", help="check parts of the taps apart")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    from dear_jax import wideconv

    n, h, c = args.batch, args.side, args.channels
    width = args.width or -(-h // 8) * 8
    if width < h or width % 8:
        parser.error(f"--width {width}: must be a multiple of 8 and at least --side {h}")
    valid = h - K + 1
    kx, kw = jax.random.split(jax.random.key(0))
    x = jax.random.normal(kx, (n, h, h, c), jnp.float32).astype(jnp.bfloat16)
    w = (jax.random.normal(kw, (K, K, c, c), jnp.float32) / np.sqrt(K * K * c)).astype(jnp.bfloat16)
    want = np.asarray(jax.jit(xla_conv)(x, w), np.float32)
    rows = {}

    def time(name, fn, *operands):
        fn = jax.jit(fn)
        jax.block_until_ready(fn(*operands))
        ms, dispatch = timed_calls(lambda i: fn(*operands), args.iters)
        rows[name] = {"us_per_call": ms * 1e3, "dispatch_us": dispatch * 1e3}
        print(f"{name:>24}: {ms * 1e3:8.1f} µs per call")
        return fn

    time("xla (cuDNN)", xla_conv, x, w)
    layer = ((w, jnp.zeros((c,), jnp.float32)),)
    time("pallas triton stack", lambda x: wideconv.conv_stack(x, layer, 0), x)
    for block in args.blocks:
        xg = to_grid(x, width, block)
        name = f"mosaic gpu, block {block}"
        out = time(name, functools.partial(conv_mgpu, width=width, block=block), xg, w)(xg, w)
        got = np.asarray(from_grid(out, n, h, width, valid), np.float32)
        err = float(np.max(np.abs(got - want)))
        rows.setdefault(name, {})["max_abs_error"] = err
        print(f"{name:>24}: max |error| against XLA {err:.4f}")
    if args.parts:
        block = args.blocks[-1]
        xg = to_grid(x, width, block)
        i, j = np.arange(K)[:, None, None, None], np.arange(K)[None, :, None, None]
        for name, keep, tiled in (
            ("all taps as registers", j >= 0, False),
            ("taps j = 0 only", j == 0, True),
            ("taps j = 1, 2 only", j > 0, True),
            ("tap (0, 0) as registers", (i == 0) & (j == 0), False),
            ("tap (0, 1) as registers", (i == 0) & (j == 1), False),
            ("tap (1, 0) as registers", (i == 1) & (j == 0), False),
        ):
            wp = jnp.where(keep, w, 0)
            fn = jax.jit(functools.partial(conv_mgpu, width=width, block=block, tiled_taps=tiled))
            got = np.asarray(from_grid(fn(xg, wp), n, h, width, valid), np.float32)
            ref = np.asarray(jax.jit(xla_conv)(x, wp), np.float32)
            bad = np.abs(got - ref) > 0.05 * (1 + np.abs(ref))
            where = np.argwhere(bad.any(-1))
            rows[f"parts: {name}"] = {
                "max_abs_error": float(np.max(np.abs(got - ref))),
                "bad_fraction": float(bad.mean()),
                "first_bad_pixels": where[:8].tolist(),
                "bad_rows_by_y": np.bincount(where[:, 1], minlength=valid).tolist()
                if len(where)
                else [],
                "bad_by_x": np.bincount(where[:, 2], minlength=valid).tolist()
                if len(where)
                else [],
            }
            print(name, rows[f"parts: {name}"])
    result = {"args": vars(args), "width": width, "valid": valid, "rows": rows}
    save_json(result, args.out)
    return result


if __name__ == "__main__":
    main()
