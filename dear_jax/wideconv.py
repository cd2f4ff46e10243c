"""Stacks of stride-1 3x3 convolutions with ReLU as Pallas (Triton) kernels on one flat layout.

Why: the stride-1 layers of the encoder (41 -> 39 -> 37 -> 35) and of the mask decoder
(35 -> 37 -> 39 -> 41, transposed) are most of a DEAR update, and on an H100 cuDNN runs them well
above the memory floor: a bf16 forward convolution at [512, 41, 41, 32] takes ~94 µs and a filter
gradient ~165 µs, where reading and writing the activations takes ~35 µs
(benchmarks/results/dispatch_h100.json). With seeds in the hybrid update, cutting each seed's
operands out of the stacked batch and stacking the results back cost another 4.1 ms of a 24.8 ms
5-seed call (benchmarks/results/profile_dear_hybrid_h100.json). Here each layer is one kernel for
all seeds (Pallas batches the grid under `jax.vmap`), with bias, ReLU and the ReLU gradient fused.

The layout. Every activation of a stack is one flat array [rows, C]: zero rows (the margin),
then each image as `size` x `size` pixels in row-major order (`size` is the largest side in the
stack), a pixel of a smaller activation sitting at the top left with zeros around it, then zero
rows again. A 3x3 tap (i, j) is then a fixed shift of the rows, `offset = i * size + j`, and the
three taps of a kernel row are 3 consecutive pixels: one load of a 4-pixel window per kernel row
([BLOCK, 4C], overlapping from row to row; the 4th pixel's weights are zero) makes a convolution
three [BLOCK, 4C] x [4C, F] products per block of rows (implicit GEMM without the im2col copy);
with WIDTH 1, nine [BLOCK, C] x [C, F] products, one per tap.
Its input gradient is the same with the shifts negated and the kernel transposed. A pixel outside
a layer's valid region is zero, so the shifts that leave a region, wrap into the next row or
cross into the next image read zeros, exactly the VALID/FULL convolution's padding; the margins
keep every load inside the array, so none is masked.

The settings below are the fastest of staged sweeps on an H100 (`bash
benchmarks/train_device.sh wcsweep`; benchmarks/RESULTS.md, "The conv stacks' settings swept"):
single-tap loads (WIDTH 1) in programs of 128 rows with 2 warps, and filter gradients with 2
warps and 3 pipeline stages. There, the bf16 DEAR update of 5 seeds at batch 512 took 4.14 ms per
seed against 5.02 with cuDNN. Slower in those sweeps: programs of several image rows that share
their windows, several blocks per program with the weights loaded once (commit 6d204e7), and
eviction policies on the loads (no gain).

`conv_stack(x, layers, pad)` is the function of
`for (k, b) in layers: x = relu(VALID conv of x zero-padded by `pad` with k, + b)`:
pad 0 for the encoder's convolutions, pad 2 for stride-1 transposed convolutions (PyTorch's
ConvTranspose2d(k=3, stride=1) is a VALID convolution of the input padded by 2 with the same
kernel, as `networks.ConvTranspose` computes it). Off GPUs the kernels run in Pallas' interpreter
(slow; for tests). tests/test_wideconv.py checks values and gradients against lax.conv.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

BLOCK = 128  # rows of one program of a convolution
NUM_WARPS = 2
WGRAD_BLOCK = 64  # rows per step of a filter gradient
WGRAD_STEPS = 32  # steps of one program of a filter gradient
WGRAD_WARPS = 2
STAGES = 3  # Triton's software pipelining of a filter gradient's steps
# Pixels per load: 4 reads a row's three taps (and one pixel more, whose weights are zero) as one
# overlapping window; 1 reads each tap on its own (9 loads per block).
WIDTH = 1
INTERPRET: bool | None = None  # Pallas' interpreter; None: off GPUs


def _interpret() -> bool:
    return jax.default_backend() != "gpu" if INTERPRET is None else INTERPRET


def supported(x_shape, layers, pad: int) -> bool:
    """Whether `conv_stack` takes this stack: square NHWC images, 3x3 kernels, channel counts
    that are powers of two >= 16 (Triton's dot), and room for the zeros that the shifts need."""
    if len(x_shape) != 4 or x_shape[1] != x_shape[2] or pad not in (0, 2) or not layers:
        return False
    sizes = _sizes(x_shape[1], len(layers), pad)
    channels = [x_shape[-1]] + [k.shape[-1] for k, _ in layers]
    return (
        all(k.shape[:2] == (3, 3) for k, _ in layers)
        and all(c >= 16 and c & (c - 1) == 0 for c in channels)
        and [k.shape[2] for k, _ in layers] == channels[:-1]
        and min(sizes) > 0
        # a FULL convolution reads two pixels beyond its input: they must be zeros of the layout
        and (pad == 0 or max(sizes[:-1]) <= max(sizes) - 2)
    )


def _sizes(size: int, n: int, pad: int) -> list[int]:
    return [size + i * (2 * pad - 2) for i in range(n + 1)]


@dataclasses.dataclass(frozen=True)
class _Layout:
    """Where the images sit in a flat array: `margin` zero rows, the images, zero rows to the
    end. The margins are as long as the farthest read of a window, so no load leaves the array
    and none needs a mask. A convolution's programs cover `conv_cover` rows from the margin on,
    a filter gradient's `wgrad_cover`; the rows past the images read and write zeros."""

    images: int
    size: int  # side of every image in the flat array

    @property
    def body(self) -> int:
        return self.images * self.size * self.size

    @property
    def margin(self) -> int:  # a window reads at most 2 * size + 2 rows before its row
        return _round_up(2 * self.size + 4, BLOCK)

    @property
    def conv_programs(self) -> int:
        return -(-self.body // BLOCK)

    @property
    def conv_cover(self) -> int:
        return self.conv_programs * BLOCK

    @property
    def wgrad_programs(self) -> int:
        return -(-self.body // (WGRAD_BLOCK * WGRAD_STEPS))

    @property
    def rows(self) -> int:
        wgrad_cover = self.wgrad_programs * WGRAD_BLOCK * WGRAD_STEPS
        # past the last program's rows, a window reads at most 2 * size + 6 rows
        reach = max(wgrad_cover - self.conv_cover, 0) + 2 * self.size + 6
        return self.margin + self.conv_cover + _round_up(reach, BLOCK)

    def flatten(self, x: jax.Array) -> jax.Array:
        """[N, h, h, C] -> [rows, C]: zeros right of and below each image, and the margins."""
        h, s = x.shape[1], self.size
        x = jnp.pad(x, ((0, 0), (0, s - h), (0, s - h), (0, 0))).reshape(-1, x.shape[-1])
        return jnp.pad(x, ((self.margin, self.rows - self.margin - self.body), (0, 0)))

    def unflatten(self, flat: jax.Array, h: int) -> jax.Array:
        """[rows, C] -> [N, h, h, C], the top-left h x h of each image."""
        x = flat[self.margin : self.margin + self.body]
        return x.reshape(self.images, self.size, self.size, flat.shape[-1])[:, :h, :h]


def _round_up(n: int, multiple: int) -> int:
    return -(-n // multiple) * multiple


def _windows(x_ref, rows, c: int):
    """x's pixels rows[k] .. rows[k] + WIDTH - 1 side by side: [len(rows), WIDTH * c]. x_ref is
    the flat array as one dimension, so one load reads overlapping windows."""
    return x_ref[rows[:, None] * c + jnp.arange(WIDTH * c, dtype=jnp.int32)[None, :]]


def _conv_kernel(*refs, bases, layout, valid, relu, has_bias, has_mask):
    x_ref, w_ref = refs[:2]
    b_ref = refs[2] if has_bias else None
    m_ref = refs[2 + has_bias] if has_mask else None
    o_ref = refs[-1]
    f, c = o_ref.shape[-1], w_ref.shape[1] // WIDTH
    p = pl.program_id(0)

    @pl.when(p < layout.conv_programs)
    def _():
        start = layout.margin + p * BLOCK
        rows = start + jnp.arange(BLOCK, dtype=jnp.int32)
        acc = jnp.zeros((BLOCK, f), jnp.float32)
        for t, base in enumerate(bases):
            acc += plt.dot(_windows(x_ref, rows + base, c), w_ref[t])
        if has_bias:
            acc += b_ref[...][None, :]
        if relu:
            acc = jnp.maximum(acc, 0.0)
        pos = rows - layout.margin
        keep = pos < layout.body
        if valid is not None:
            pos = jax.lax.rem(pos, layout.size * layout.size)
            keep &= (jax.lax.div(pos, layout.size) < valid) & (
                jax.lax.rem(pos, layout.size) < valid
            )
        keep = keep[:, None]
        if has_mask:
            keep &= m_ref[pl.ds(start, BLOCK), :] > 0
        o_ref[pl.ds(start, BLOCK), :] = jnp.where(keep, acc, 0.0).astype(o_ref.dtype)

    @pl.when(p >= layout.conv_programs)
    def _():  # the margins: zeros
        z = p - layout.conv_programs
        head = layout.margin // BLOCK
        end = layout.margin + layout.conv_cover
        first = jnp.where(z < head, z * BLOCK, end + (z - head) * BLOCK)
        o_ref[pl.ds(first, BLOCK), :] = jnp.zeros((BLOCK, f), o_ref.dtype)


def _conv(x, w, bases, layout, *, bias=None, relu=False, valid=None, mask=None):
    """out[p] = sum_t window(x, p + bases[t]) @ w[t] (+ bias, ReLU), zero outside `valid` x
    `valid` (if given) and in the margins, and zero where `mask` is not positive (if given)."""
    f = w.shape[-1]
    args = [x.reshape(-1), w.astype(x.dtype)]
    if bias is not None:
        args.append(bias.astype(jnp.float32))
    if mask is not None:
        args.append(mask)
    zero_blocks = (layout.rows - layout.conv_cover) // BLOCK
    return pl.pallas_call(
        functools.partial(
            _conv_kernel,
            bases=bases,
            layout=layout,
            valid=valid,
            relu=relu,
            has_bias=bias is not None,
            has_mask=mask is not None,
        ),
        out_shape=jax.ShapeDtypeStruct((layout.rows, f), x.dtype),
        grid=(layout.conv_programs + zero_blocks,),
        interpret=_interpret(),
        # Triton's parameters also pick Pallas' Triton backend (not Mosaic GPU).
        compiler_params=plt.CompilerParams(num_warps=NUM_WARPS, num_stages=STAGES),
    )(*args)


def _wgrad_kernel(x_ref, g_ref, w_ref, b_ref, *, bases, layout):
    f, c = g_ref.shape[-1], w_ref.shape[2] // WIDTH
    p = pl.program_id(0)

    def step(s, carry):
        accs, bacc = carry
        start = layout.margin + (p * WGRAD_STEPS + s) * WGRAD_BLOCK
        rows = start + jnp.arange(WGRAD_BLOCK, dtype=jnp.int32)
        g = g_ref[pl.ds(start, WGRAD_BLOCK), :]
        out = tuple(
            acc + plt.dot(_windows(x_ref, rows + base, c), g, trans_a=True)
            for acc, base in zip(accs, bases)
        )
        return out, bacc + jnp.sum(g.astype(jnp.float32), axis=0)

    zeros = tuple(jnp.zeros((WIDTH * c, f), jnp.float32) for _ in bases)
    accs, bacc = jax.lax.fori_loop(0, WGRAD_STEPS, step, (zeros, jnp.zeros((f,), jnp.float32)))
    for t in range(len(bases)):
        w_ref[p, t] = accs[t]
    b_ref[p] = bacc


def _wgrad(x, g, bases, layout):
    """(sum_p window(x, p + bases[t])^T g[p] for each t, sum_p g[p]), in float32."""
    c, f = x.shape[-1], g.shape[-1]
    programs = layout.wgrad_programs
    w, b = pl.pallas_call(
        functools.partial(_wgrad_kernel, bases=bases, layout=layout),
        out_shape=(
            jax.ShapeDtypeStruct((programs, len(bases), WIDTH * c, f), jnp.float32),
            jax.ShapeDtypeStruct((programs, f), jnp.float32),
        ),
        grid=(programs,),
        interpret=_interpret(),
        compiler_params=plt.CompilerParams(num_warps=WGRAD_WARPS, num_stages=STAGES),
    )(x.reshape(-1), g)
    return w.sum(0), b.sum(0)


def _plan(x_shape, pad, n):
    sizes = _sizes(x_shape[1], n, pad)
    return _Layout(x_shape[0], max(sizes)), sizes


def _bases(pad: int, size: int, backward: bool) -> tuple[int, ...]:
    """Where each window of a layer starts, relative to the output pixel. Forward, tap (i, j)
    reads pixel (i - pad, j - pad) from it; backward (the input gradient), tap (i, j') reads
    pixel (pad - i, pad - 2 + j') with kernel tap (i, 2 - j')."""
    rows, cols = range(3), range(0, 3, WIDTH)
    if backward:
        return tuple((pad - i) * size + pad - 2 + j for i in rows for j in cols)
    return tuple((i - pad) * size + j - pad for i in rows for j in cols)


def _pack(kernel: jax.Array, backward: bool) -> jax.Array:
    """[3, 3, C, F] -> one [WIDTH * C, F] matrix per window (the kernel transposed and its
    columns reversed for the input gradient; rows of a 4th pixel zero)."""
    if backward:
        kernel = jnp.swapaxes(kernel, 2, 3)[:, ::-1]
    if WIDTH == 4:
        kernel = jnp.pad(kernel, ((0, 0), (0, 1), (0, 0), (0, 0)))
    return kernel.reshape(-1, WIDTH * kernel.shape[2], kernel.shape[3])


def _unpack(w: jax.Array, c: int) -> jax.Array:
    """The filter gradient's windows [groups, WIDTH * C, F] -> [3, 3, C, F]."""
    return w.reshape(3, -1, c, w.shape[-1])[:, :3]


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv_stack(x: jax.Array, layers: tuple, pad: int) -> jax.Array:
    """relu(VALID conv(zero-pad(x, pad), k) + b) for each (k, b) of `layers`, in x's dtype.

    x: [N, H, H, C]; each k: [3, 3, C_in, C_out]; each b: [C_out]. Returns [N, H', H', C_out]
    with H' = H + len(layers) * (2 * pad - 2). See `supported` for the shapes it takes.
    """
    return _forward(x, layers, pad)[0]


def _forward(x, layers, pad):
    layout, sizes = _plan(x.shape, pad, len(layers))
    bases = _bases(pad, layout.size, backward=False)
    acts = [layout.flatten(x)]
    for (k, b), size in zip(layers, sizes[1:]):
        w = _pack(k, backward=False)
        acts.append(_conv(acts[-1], w, bases, layout, bias=b, relu=True, valid=size))
    return layout.unflatten(acts[-1], sizes[-1]), acts


def _conv_stack_fwd(x, layers, pad):
    y, acts = _forward(x, layers, pad)
    return y, (acts, layers)


def _conv_stack_bwd(pad, residuals, g):
    acts, layers = residuals
    n = len(layers)
    layout, sizes = _plan((g.shape[0], g.shape[1] - n * (2 * pad - 2)), pad, n)
    bases = _bases(pad, layout.size, backward=False)
    back = _bases(pad, layout.size, backward=True)
    # The gradient at the last layer's pre-activations, in the layout.
    g = jnp.where(acts[-1] > 0, layout.flatten(g.astype(acts[-1].dtype)), 0)
    grads = []
    for i in reversed(range(n)):
        k = layers[i][0]
        dk, db = _wgrad(acts[i], g, bases, layout)
        grads.append((_unpack(dk, k.shape[2]).astype(k.dtype), db.astype(layers[i][1].dtype)))
        # Input gradient, with the ReLU gradient of the layer below (the stack's input has none).
        w = _pack(k, backward=True)
        g = _conv(g, w, back, layout, mask=acts[i] if i else None)
    dx = layout.unflatten(g, sizes[0])
    return dx, tuple(reversed(grads))


conv_stack.defvjp(_conv_stack_fwd, _conv_stack_bwd)
