"""Stacks of convolutions (with ReLU) as Pallas (Triton) kernels on one flat layout.

Why: the stride-1 layers of the encoder (41 -> 39 -> 37 -> 35) and of the mask decoder
(35 -> 37 -> 39 -> 41, transposed) are most of a DEAR update, and on an H100 cuDNN runs them well
above the memory floor: a bf16 forward convolution at [512, 41, 41, 32] takes ~94 µs and a filter
gradient ~165 µs, where reading and writing the activations takes ~35 µs
(benchmarks/results/dispatch_h100.json). With seeds in the hybrid update, cutting each seed's
operands out of the stacked batch and stacking the results back cost another 4.1 ms of a 24.8 ms
5-seed call (benchmarks/results/profile_dear_hybrid_h100.json). Here each layer is one kernel for
all seeds (Pallas batches the grid under `jax.vmap`), with bias, ReLU and the ReLU gradient fused.
The strided layers around them join the stacks (`networks.ConvTrunk`, `networks.PoolDecoder`):
the encoder's stride-2 first layer reads the uint8 frames themselves (through the random
shift's crops, so no shifted copy is made), and the decoder's last layer, a stride-2 transposed
convolution, is the 2x2 convolution that produces its four output phases.

The layout. Every activation of a stack is one flat array [rows, C]: zero rows (the margin),
then each image as `size` x `size` pixels in row-major order (`size` is the largest side in the
stack), a pixel of a smaller activation sitting at the top left with zeros around it, then zero
rows again. A kernel tap (i, j) of a layer padded by p is then a fixed shift of the rows,
`offset = (i - p) * size + (j - p)`, so a convolution is one [BLOCK, C] x [C, F] product per tap
for each block of rows (implicit GEMM without the im2col copy). Its input gradient is the same
with the shifts negated and the kernel transposed. A pixel outside a layer's valid region is
zero, so the shifts that leave a region, wrap into the next row or cross into the next image
read zeros, exactly the VALID convolution of the zero-padded input; the margins keep every load
inside the array, so none is masked.

The settings below are the fastest of staged sweeps on an H100 (`bash
benchmarks/train_device.sh wcsweep`; benchmarks/RESULTS.md, "The conv stacks' settings swept"):
programs of 128 rows with 2 warps, and filter gradients with 2 warps and 3 pipeline stages.
There, the bf16 DEAR update of 5 seeds at batch 512 took 4.14 ms per seed against 5.02 with
cuDNN. Slower in those sweeps and removed: loads of 4-pixel windows (3 taps and a zero-weighted
pixel per load), programs of several image rows that share their windows, several blocks per
program with the weights loaded once (commit 6d204e7), and eviction policies on the loads.

`conv_stack(x, layers, pads)` is the function of
`for (k, b), p in zip(layers, pads): x = relu(VALID conv of x zero-padded by p with k, + b)`,
the last ReLU optional. PyTorch's ConvTranspose2d(k=3, stride=1) is such a layer with pad 2
(`networks.ConvTranspose`). Off GPUs the kernels run in Pallas' interpreter (slow; for tests).
tests/test_wideconv.py checks values and gradients against lax.conv.
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
INTERPRET: bool | None = None  # Pallas' interpreter; None: off GPUs


def _interpret() -> bool:
    return jax.default_backend() != "gpu" if INTERPRET is None else INTERPRET


def channels_for(n: int) -> int:
    """The channel count the kernels compute n channels with: the next power of two, >= 16."""
    return max(16, 1 << (n - 1).bit_length())


def _pads(pads, n: int) -> tuple[int, ...]:
    return (pads,) * n if isinstance(pads, int) else tuple(pads)


def supported(x, layers, pads, stride: int = 1, shift: int = 0) -> bool:
    """Whether `conv_stack` takes this stack (x: an array or its shape and dtype): square NHWC
    images, square kernels no wider than 3 padded by less than their width, channel counts that
    are powers of two >= 16 (Triton's dot), and room for the zeros that the shifts need. A
    strided first layer reads integer pixels of at most 16 channels, unpadded (and only they
    may be read through a random shift)."""
    pads = _pads(pads, len(layers))
    if x.ndim != 4 or x.shape[1] != x.shape[2] or not layers or len(pads) != len(layers):
        return False
    kernels = [k.shape for k, _ in layers]
    channels = [x.shape[-1]] + [k[-1] for k in kernels]
    if not all(k[0] == k[1] <= 3 and 0 <= p < k[0] for k, p in zip(kernels, pads)):
        return False
    if stride > 1 and (pads[0] or x.shape[-1] > 16 or jnp.issubdtype(x.dtype, jnp.floating)):
        return False
    if shift and stride == 1:  # a shift is read with the pixels of a strided first layer
        return False
    sizes = _sizes(x.shape[1], kernels, pads, stride)
    first = int(stride > 1)  # the first layer in the layout
    side = max(sizes[first:])
    return (
        all(c >= 16 and c & (c - 1) == 0 for c in channels[first:])
        and [k[2] for k in kernels] == channels[:-1]
        and min(sizes) > 0
        # a padded layer reads p pixels beyond its input on each side: zeros of the layout
        and all(sizes[i] + pads[i] <= side for i in range(first, len(layers)))
    )


def _sizes(size: int, kernels, pads, stride: int = 1) -> list[int]:
    """The side of the input and of each layer's output."""
    sizes = [size]
    for i, (k, p) in enumerate(zip(kernels, pads)):
        s = stride if i == 0 else 1
        sizes.append((sizes[-1] + 2 * p - k[0]) // s + 1)
    return sizes


@dataclasses.dataclass(frozen=True)
class _Layout:
    """Where the images sit in a flat array: `margin` zero rows, the images, zero rows to the
    end. The margins are as long as the farthest read of a tap (`reach` rows away), so no load
    leaves the array and none needs a mask. A convolution's programs cover `conv_cover` rows
    from the margin on, a filter gradient's `wgrad_cover`; the rows past the images read and
    write zeros."""

    images: int
    size: int  # side of every image in the flat array
    reach: int  # largest |offset| of a tap, forward or backward

    @property
    def body(self) -> int:
        return self.images * self.size * self.size

    @property
    def margin(self) -> int:
        return _round_up(self.reach, BLOCK)

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
        tail = max(wgrad_cover - self.conv_cover, 0) + self.reach
        return self.margin + self.conv_cover + _round_up(tail, BLOCK)

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


@dataclasses.dataclass(frozen=True)
class _Pixels:
    """The input of a strided first layer: x itself ([N, side, side, channels], not in the
    layout), read for each output pixel of the layout one kernel row at a time: the `kernel`
    pixels of row i are kernel * channels consecutive values, one load of `width` lanes (a
    power of two >= 16; the lanes past them read zeros)."""

    side: int
    channels: int
    stride: int
    kernel: int
    valid: int  # side of the layer's output
    shift: int = 0  # the pad of a random shift read with the pixels (augment.shift); 0: none

    @property
    def width(self) -> int:
        return channels_for(self.kernel * self.channels)

    def loader(self, x_ref, crop_ref, rows, layout, dtype):
        """kernel row i -> [len(rows), width]: for each output pixel at `rows` of the layout,
        its input pixels of that row (zeros outside the output's valid pixels). With a shift,
        the pixels of each image's crop at its (dy, dx) in crop_ref (flat [N * 2]): pixel
        (Y, X) of the crop is pixel (clip(Y + dy - shift), clip(X + dx - shift)) of the image,
        as `augment.shift` crops the edge-padded image."""
        pos = rows - layout.margin
        image, pixel = jax.lax.div(pos, layout.size**2), jax.lax.rem(pos, layout.size**2)
        y, x = jax.lax.div(pixel, layout.size), jax.lax.rem(pixel, layout.size)
        keep = (pos < layout.body) & (y < self.valid) & (x < self.valid)
        base = ((image * self.side + self.stride * y) * self.side + self.stride * x) * self.channels
        base = jnp.where(keep, base, 0)
        lanes = jnp.arange(self.width, dtype=jnp.int32)
        mask = keep[:, None] & (lanes < self.kernel * self.channels)[None, :]
        if self.shift:
            return self._shifted(x_ref, crop_ref, image, y, x, keep, lanes, mask, dtype)

        def load(i):
            idx = base[:, None] + i * self.side * self.channels + lanes[None, :]
            return plt.load(x_ref.at[idx], mask=mask, other=0).astype(dtype)

        return load

    def _shifted(self, x_ref, crop_ref, image, y, x, keep, lanes, mask, dtype):
        image = jnp.where(keep, image, 0)
        dy = plt.load(crop_ref.at[2 * image], mask=keep, other=0)
        dx = plt.load(crop_ref.at[2 * image + 1], mask=keep, other=0)
        last = self.side - 1
        # lane l holds channel l % C of the row's pixel l // C
        pixel, channel = jax.lax.div(lanes, self.channels), jax.lax.rem(lanes, self.channels)
        col = self.stride * x + dx - self.shift
        col = jnp.clip(col[:, None] + pixel[None, :], 0, last)

        def load(i):
            row = jnp.clip(self.stride * y + i + dy - self.shift, 0, last)
            idx = ((image * self.side + row)[:, None] * self.side + col) * self.channels
            return plt.load(x_ref.at[idx + channel[None, :]], mask=mask, other=0).astype(dtype)

        return load


def _loader(x_ref, crop_ref, rows, offsets, c: int, layout, pixels, dtype):
    """tap t -> x's pixels for the output pixels at `rows`, [len(rows), c], in `dtype`: in
    the layout, the rows shifted by offsets[t] (x_ref is the flat array as one dimension); with
    `pixels`, kernel row t as `_Pixels` reads it."""
    if pixels is not None:
        return pixels.loader(x_ref, crop_ref, rows, layout, dtype)
    lanes = jnp.arange(c, dtype=jnp.int32)[None, :]
    return lambda t: x_ref[(rows + offsets[t])[:, None] * c + lanes].astype(dtype)


def _conv_kernel(*refs, offsets, layout, valid, relu, has_bias, has_mask, pixels):
    x_ref, *refs, o_ref = refs
    crop_ref = refs.pop(0) if pixels and pixels.shift else None
    w_ref = refs.pop(0)
    b_ref = refs.pop(0) if has_bias else None
    m_ref = refs.pop(0) if has_mask else None
    f, c = o_ref.shape[-1], w_ref.shape[1]
    p = pl.program_id(0)

    @pl.when(p < layout.conv_programs)
    def _():
        start = layout.margin + p * BLOCK
        rows = start + jnp.arange(BLOCK, dtype=jnp.int32)
        taps = _loader(x_ref, crop_ref, rows, offsets, c, layout, pixels, w_ref.dtype)
        acc = jnp.zeros((BLOCK, f), jnp.float32)
        for t in range(w_ref.shape[0]):
            acc += plt.dot(taps(t), w_ref[t])
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


def _conv(x, w, offsets, layout, *, bias=None, relu=False, valid=None, mask=None, pixels=None):
    """out[q] = sum_t x[q + offsets[t]] @ w[t] (+ bias, ReLU) in w's dtype, zero outside
    `valid` x `valid` (if given) and in the margins, and zero where `mask` is not positive (if
    given). x may be of another dtype (uint8 pixels): each tap is converted to w's. With
    `pixels`, x is a strided layer's input as it is, read as `_Pixels` says (with a shift, x is
    (pixels, crop offsets))."""
    f = w.shape[-1]
    args = [*_pixel_args(x, pixels), w]
    if bias is not None:
        args.append(bias.astype(jnp.float32))
    if mask is not None:
        args.append(mask)
    zero_blocks = (layout.rows - layout.conv_cover) // BLOCK
    return pl.pallas_call(
        functools.partial(
            _conv_kernel,
            offsets=offsets,
            layout=layout,
            valid=valid,
            relu=relu,
            has_bias=bias is not None,
            has_mask=mask is not None,
            pixels=pixels,
        ),
        out_shape=jax.ShapeDtypeStruct((layout.rows, f), w.dtype),
        grid=(layout.conv_programs + zero_blocks,),
        interpret=_interpret(),
        # Triton's parameters also pick Pallas' Triton backend (not Mosaic GPU).
        compiler_params=plt.CompilerParams(num_warps=NUM_WARPS, num_stages=STAGES),
    )(*args)


def _wgrad_kernel(*refs, offsets, layout, pixels):
    x_ref, *refs, w_ref, b_ref = refs
    crop_ref = refs.pop(0) if pixels and pixels.shift else None
    g_ref = refs.pop(0)
    f, c, n = g_ref.shape[-1], w_ref.shape[2], w_ref.shape[1]
    p = pl.program_id(0)

    def step(s, carry):
        accs, bacc = carry
        start = layout.margin + (p * WGRAD_STEPS + s) * WGRAD_BLOCK
        rows = start + jnp.arange(WGRAD_BLOCK, dtype=jnp.int32)
        g = g_ref[pl.ds(start, WGRAD_BLOCK), :]
        taps = _loader(x_ref, crop_ref, rows, offsets, c, layout, pixels, g.dtype)
        out = tuple(acc + plt.dot(taps(t), g, trans_a=True) for t, acc in enumerate(accs))
        return out, bacc + jnp.sum(g.astype(jnp.float32), axis=0)

    zeros = tuple(jnp.zeros((c, f), jnp.float32) for _ in range(n))
    accs, bacc = jax.lax.fori_loop(0, WGRAD_STEPS, step, (zeros, jnp.zeros((f,), jnp.float32)))
    for t in range(n):
        w_ref[p, t] = accs[t]
    b_ref[p] = bacc


def _pixel_args(x, pixels) -> list:
    """A layer's input as the kernels take it: flat, and with a shift its crop offsets."""
    if pixels is not None and pixels.shift:
        return [x[0].reshape(-1), x[1].reshape(-1).astype(jnp.int32)]
    return [x.reshape(-1)]


def _wgrad(x, g, offsets, layout, pixels=None):
    """(sum_q x[q + offsets[t]]^T g[q] for each t, sum_q g[q]), in float32 (x read as
    `_Pixels` says, if given)."""
    c, f = (pixels.width if pixels else x.shape[-1]), g.shape[-1]
    taps = pixels.kernel if pixels else len(offsets)
    programs = layout.wgrad_programs
    w, b = pl.pallas_call(
        functools.partial(_wgrad_kernel, offsets=offsets, layout=layout, pixels=pixels),
        out_shape=(
            jax.ShapeDtypeStruct((programs, taps, c, f), jnp.float32),
            jax.ShapeDtypeStruct((programs, f), jnp.float32),
        ),
        grid=(programs,),
        interpret=_interpret(),
        compiler_params=plt.CompilerParams(num_warps=WGRAD_WARPS, num_stages=STAGES),
    )(*_pixel_args(x, pixels), g)
    return w.sum(0), b.sum(0)


def _plan(x_shape, layers, pads, stride, shift=0):
    """(layout, the sides of the input and of each layer's output, the strided first layer's
    `_Pixels` or None)."""
    kernels = [k.shape for k, _ in layers]
    sizes = _sizes(x_shape[1], kernels, pads, stride)
    first = int(stride > 1)
    size = max(sizes[first:])
    reach = max(
        [max(p, k[0] - 1 - p) * (size + 1) for k, p in zip(kernels[first:], pads[first:])],
        default=0,
    )
    pixels = (
        _Pixels(x_shape[1], x_shape[-1], stride, kernels[0][0], sizes[1], shift) if first else None
    )
    return _Layout(x_shape[0], size, reach), sizes, pixels


def _offsets(k: int, pad: int, size: int) -> tuple[int, ...]:
    """Where tap (i, j) of a k x k layer padded by `pad` reads, relative to the output pixel,
    in the order of the kernel's taps. The input gradient reads at the negated offsets."""
    return tuple((i - pad) * size + j - pad for i in range(k) for j in range(k))


def _taps_of(k: jax.Array, pixels) -> jax.Array:
    """[K, K, C, F] -> one [C, F] matrix per tap; for a strided first layer, one
    [pixels.width, F] matrix per kernel row (its K * C rows, then zeros)."""
    if pixels is None:
        return k.reshape(-1, *k.shape[2:])
    k = k.reshape(k.shape[0], -1, k.shape[-1])
    return jnp.pad(k, ((0, 0), (0, pixels.width - k.shape[1]), (0, 0)))


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3, 4, 5, 6))
def conv_stack(
    x, layers: tuple, pads, relu_last=True, dtype=None, stride=1, shift=0, crops=None
) -> jax.Array:
    """relu(VALID conv(zero-pad(x, p), k) + b) for each (k, b) of `layers` and p of `pads` (one
    int: every layer's), the last ReLU only with `relu_last`; computed in `dtype` (default x's;
    an integer x, e.g. uint8 pixels, needs one and gets no gradient).

    The first layer may have a `stride`: then x is integer pixels, read as they are, and its
    pad is 0. Such pixels may be read through a random shift (`augment.shift` with pad `shift`
    > 0 at each image's offsets (dy, dx) in `crops`, [N, 2]), as if x were the shifted images.

    x: [N, H, H, C]; each k: [K, K, C_in, C_out]; each b: [C_out]. Returns [N, H', H', C_out].
    See `supported` for the shapes it takes.
    """
    return _forward(x, layers, pads, relu_last, dtype, stride, shift, crops)[0]


def _forward(x, layers, pads, relu_last, dtype, stride, shift, crops):
    dtype = dtype or x.dtype
    pads = _pads(pads, len(layers))
    layout, sizes, pixels = _plan(x.shape, layers, pads, stride, shift)
    if pixels is None:
        acts = [layout.flatten(x)]
    else:  # read as they are (through the crops, with a shift)
        acts = [(x, crops) if shift else x]
    for i, ((k, b), p) in enumerate(zip(layers, pads)):
        first = pixels if i == 0 else None
        w = _taps_of(k, first).astype(dtype)
        offsets = _offsets(k.shape[0], p, layout.size)
        relu = relu_last or i < len(layers) - 1
        acts.append(
            _conv(acts[-1], w, offsets, layout, bias=b, relu=relu, valid=sizes[i + 1], pixels=first)
        )
    return layout.unflatten(acts[-1], sizes[-1]), acts


def _conv_stack_fwd(x, layers, pads, relu_last, dtype, stride, shift, crops):
    y, acts = _forward(x, layers, pads, relu_last, dtype, stride, shift, crops)
    # An empty array of x's image shape and dtype: the backward pass's plan and dx need them.
    return y, (acts, layers, jnp.zeros((0, *x.shape[1:]), x.dtype))


def _conv_stack_bwd(pads, relu_last, dtype, stride, shift, residuals, g):
    acts, layers, x_like = residuals
    pads = _pads(pads, len(layers))
    layout, sizes, pixels = _plan((g.shape[0], *x_like.shape[1:]), layers, pads, stride, shift)
    # The gradient at the last layer's output (its pre-activations, after a ReLU), in the layout.
    g = layout.flatten(g.astype(acts[-1].dtype))
    if relu_last:
        g = jnp.where(acts[-1] > 0, g, 0)
    grads = []
    for i in reversed(range(len(layers))):
        k, b = layers[i]
        first = pixels if i == 0 else None
        offsets = _offsets(k.shape[0], pads[i], layout.size)
        dk, db = _wgrad(acts[i], g, offsets, layout, first)
        dk = dk[:, : k.shape[1] * k.shape[2]] if first else dk
        grads.append((dk.reshape(k.shape).astype(k.dtype), db.astype(b.dtype)))
        if i == 0 and not jnp.issubdtype(x_like.dtype, jnp.floating):
            return None, tuple(reversed(grads)), None
        # Input gradient, with the ReLU gradient of the layer below (the stack's input has none).
        w = jnp.swapaxes(_taps_of(k, None), 1, 2).astype(g.dtype)
        g = _conv(g, w, tuple(-o for o in offsets), layout, mask=acts[i] if i else None)
    dx = layout.unflatten(g, sizes[0]).astype(x_like.dtype)
    return dx, tuple(reversed(grads)), None


conv_stack.defvjp(_conv_stack_fwd, _conv_stack_bwd)
