"""The filter gradient of a stride-1 VALID NHWC convolution as one Pallas (Triton) kernel.

Why: on an H100, cuDNN's filter gradient at the encoder's shapes costs the host 175-200 µs to
launch, more than the 163 µs it runs, and a DEAR update has 9 per seed
(benchmarks/results/dispatch_h100.json, measured at commit 486829d). This kernel is one
launch that reads the input and the output gradient once.

Measured on an H100 (commit 5e1603e, benchmarks/results/wgrad_h100.json): the
encoder's three stride-1 filter gradients for 5 seeds at batch 512 take 2.28 ms (1 image per
program, 2 warps; the defaults below) against cuDNN's 3.08 ms once per seed, and the host
launches them in 0.09 ms against 1.41. In the whole update it saves the host 1.2-1.5 ms per call
but the GPU no time: DEAR 5.12 ms per seed-update against 5.03 with cuDNN, DrQ-v2 3.13 against
3.03 (benchmarks/results/update_pallas_h100.json). So `agent.filter_gradient` stays "cudnn".

dW[i, j, c, f] = sum over n, h, w of x[n, h + i, w + j, c] * g[n, h, w, f]. Program p takes
`images` images; for each output row it loads the row of g ([Wo, F], padded to a power of two
and masked) and, per tap (i, j), the matching row segment of x ([Wo, C], masked), and adds
x_rowᵀ g_row to that tap's [C, F] accumulator (float32). The partial sums of the programs are
added by XLA afterwards. Under `jax.vmap` the kernel gains a grid axis (Pallas' batching rule),
so the seeds' filter gradients stay one launch.

Off GPUs it runs in Pallas' interpreter (slow; for tests). `supported` says which shapes it
takes; the caller keeps cuDNN for the others.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

MAX_WIDTH = 128  # output rows wider than this stay on cuDNN
IMAGES = 1  # images per program
NUM_WARPS = 2


def _pow2(n: int) -> int:
    return 1 << max(n - 1, 0).bit_length()


def supported(x_shape, kernel_shape, stride: int) -> bool:
    """Whether `filter_gradient` takes this convolution: stride 1, channel counts that are
    powers of two >= 16 (Triton's dot), output rows no wider than MAX_WIDTH."""
    c, f = kernel_shape[2], kernel_shape[3]
    wo = x_shape[-2] - kernel_shape[1] + 1
    return (
        stride == 1
        and all(n >= 16 and n == _pow2(n) for n in (c, f))
        and 0 < wo <= MAX_WIDTH
        and len(x_shape) == 4
    )


def _kernel(x_ref, g_ref, o_ref, *, k: int, width: int, ho: int, wo: int, bw: int, images: int):
    # x_ref [N, H*W, C], g_ref [N, Ho*Wo, F], o_ref [P, k*k, C, F] (float32)
    p = pl.program_id(0)
    c, f = x_ref.shape[-1], g_ref.shape[-1]
    valid = jnp.arange(bw) < wo
    x_mask = jnp.broadcast_to(valid[:, None], (bw, c))
    g_mask = jnp.broadcast_to(valid[:, None], (bw, f))

    def row(i, accs):
        n = p * images + jax.lax.div(i, ho)  # i >= 0: truncating division, as Triton lowers
        r = jax.lax.rem(i, ho)
        g = plt.load(g_ref.at[n, pl.ds(r * wo, bw), :], mask=g_mask, other=0.0)
        out = []
        for t in range(k * k):
            start = (r + t // k) * width + t % k
            x = plt.load(x_ref.at[n, pl.ds(start, bw), :], mask=x_mask, other=0.0)
            out.append(accs[t] + plt.dot(x, g, trans_a=True).astype(jnp.float32))
        return tuple(out)

    zeros = tuple(jnp.zeros((c, f), jnp.float32) for _ in range(k * k))
    accs = jax.lax.fori_loop(0, images * ho, row, zeros)
    for t in range(k * k):
        o_ref[p, t] = accs[t]


@functools.partial(jax.jit, static_argnames=("kernel_size", "images", "num_warps", "interpret"))
def filter_gradient(
    x: jax.Array,
    g: jax.Array,
    kernel_size: int,
    images: int = IMAGES,
    num_warps: int = NUM_WARPS,
    interpret: bool | None = None,
) -> jax.Array:
    """dW [k, k, C, F] (float32) of `lax.conv_general_dilated(x, W, (1, 1), "VALID", NHWC/HWIO)`
    for x [N, H, W, C] and the output's gradient g [N, H-k+1, W-k+1, F]. Each program takes
    `images` images and runs on `num_warps` warps (timed at commit 5e1603e, wgrad_h100.json)."""
    n, h, width, c = x.shape
    k = kernel_size
    ho, wo, f = g.shape[1], g.shape[2], g.shape[3]
    if (ho, wo) != (h - k + 1, width - k + 1) or g.shape[0] != n:
        raise ValueError(f"g {g.shape} is not the gradient of a {k}x{k} VALID conv of x {x.shape}")
    if n % images:
        raise ValueError(f"images={images} must divide the batch ({n})")
    if interpret is None:
        interpret = jax.default_backend() != "gpu"
    programs = n // images
    partials = pl.pallas_call(
        functools.partial(
            _kernel, k=k, width=width, ho=ho, wo=wo, bw=_pow2(max(wo, 16)), images=images
        ),
        out_shape=jax.ShapeDtypeStruct((programs, k * k, c, f), jnp.float32),
        grid=(programs,),
        interpret=interpret,
        # Triton's parameters also pick Pallas' Triton backend (not Mosaic GPU).
        compiler_params=plt.CompilerParams(num_warps=num_warps, num_stages=1),
    )(x.reshape(n, h * width, c), g.reshape(n, ho * wo, f))
    return partials.sum(0).reshape(k, k, c, f)
