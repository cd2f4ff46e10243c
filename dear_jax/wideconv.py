"""Stacks of convolutions (with ReLU) as Pallas (Triton) kernels on rows of pixels.

What this file owns: the encoder's conv trunk and the decoders' convolutions as one kernel per
layer and pass (forward, input gradient, filter gradient) for all vmapped seeds at once (Pallas
batches the grid under `jax.vmap`), with bias, ReLU and the ReLU gradient fused. Why: cuDNN runs
these small-channel layers well above the memory floor, and in the hybrid update cutting each
seed's operands out of the stacked batch and stacking the results back costs as much again
(benchmarks/RESULTS.md, "The update" and "Roofline of the updates").

The layout. Every activation of a stack is its pixels as rows, [N * side * side, C] (`_Grid`;
zero rows pad it to a multiple of the blocks). A convolution is one [BLOCK, C] x [C, F] product
per kernel tap for each block of output rows (implicit GEMM without the im2col copy): for tap
(i, j) of a layer padded by p, output pixel (y, x) of image n reads input row
(n * side_in + y + i - p) * side_in + x + j - p, computed once per row from the output row's
(n, y, x), the tap adding a constant. A VALID layer's taps never leave its input; the taps that
can reach a padded layer's padding are masked loads that read zeros there (`_Pass`). Its input
gradient is the convolution of the output gradient padded by k - 1 - p with the kernel flipped
and transposed. The taps run as a loop, which Triton software-pipelines (`TAP_LOOP`).

The layers around the stride-1 ones join the stacks (`networks.ConvTrunk`,
`networks.PoolDecoder`): the encoder's stride-2 first layer reads the uint8 frames themselves,
a kernel row of pixels per load, through the random shift's crops, so no shifted copy is made
(`_Pixels`); the decoder's last layer, a stride-2 transposed convolution, is the 2x2 convolution
that produces its four output phases. PyTorch's ConvTranspose2d(k=3, stride=1) is a layer with
pad 2 (`networks.ConvTranspose`).

Filter gradients sum x^T g over the rows in programs of WGRAD_STEPS steps of WGRAD_BLOCK rows,
each program writing partial sums that XLA adds up. A 3 x 3 (or 2 x 2) layer steps over anchors
(`_Anchors`): each step loads k blocks of the input and k of the output gradient rather than
k * k of the input and one of the gradient.

`conv_stack(x, layers, pads)` is the function of
`for (k, b), p in zip(layers, pads): x = relu(VALID conv of x zero-padded by p with k, + b)`,
the last ReLU optional. `conv_stack_loss` is such a stack with a loss of its last layer's output
fused into that layer's kernel (`LOSSES`: the mask decoder's binary cross-entropy, SEAR's
reconstruction error), whose output is then the loss's gradient: the logits are never written.

The settings below (block sizes, warps, pipeline stages, switches) are the fastest found by
`python -m benchmarks.update ... --kernels` on an H100 and an H200; the measurements, and the
variants that were slower and removed, are in benchmarks/RESULTS.md ("The conv kernels'
settings"). Off GPUs the kernels run in Pallas' interpreter (slow; for tests).
tests/test_wideconv.py checks values and gradients against lax.conv.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

BLOCK = 128  # rows of one program of a convolution
NUM_WARPS = 4
WGRAD_BLOCK = 64  # rows per step of a filter gradient
WGRAD_STEPS = 32  # steps of one program of a filter gradient (at most; see below)
# On GPUs, a filter gradient's programs may take fewer steps (halving WGRAD_STEPS, down to 1)
# until its grid, over every vmapped seed, has at least WGRAD_MIN_PROGRAMS programs; 0: always
# WGRAD_STEPS. A lone seed's 35 x 35 layer at batch 512 has 307 programs of 32 steps, ~2 per SM of
# an H100, where five seeds have 1,535; more programs also mean more partial sums to add up.
# Timed for one seed on an H200 (benchmarks/RESULTS.md, "The conv kernels' settings"): 1024 and
# 2048 were no faster than 0, so it stays off. With it set, how many seeds share a device
# changes a filter gradient's summation order (its rounding): the seed axes and splits over
# devices are then no longer the same bit for bit.
WGRAD_MIN_PROGRAMS = 0
WGRAD_WARPS = 2
# A filter gradient's products as g^T x rather than x^T g (its result then transposed in XLA).
# Over output rows, where a step's one block of g meets k * k blocks of x, g^T x transposes one
# block a step instead of k * k; it was 1-15% faster there (H200, benchmarks/RESULTS.md). Over
# anchors, both transpose k blocks a step, and x^T g was level or faster.
WGRAD_G_FIRST = False
# A padded or VALID layer's filter gradient stepping over anchors rather than output rows
# (`_Anchors`): a step loads k blocks of the input and k of the output gradient rather than
# k * k and one. On an H200 every method's update took 6-19% less time (benchmarks/RESULTS.md).
WGRAD_ANCHORS = True
STAGES = 3  # Triton's software pipelining of a filter gradient's steps (and of looped taps)
# A convolution's taps as a loop (which Triton software-pipelines) rather than unrolled, and
# its pipeline's stages.
TAP_LOOP = True
CONV_STAGES = 3
# The float32 dots' precision on GPUs: None lets them run in TF32, as XLA's float32 convolutions
# do there by default; jax.lax.Precision.HIGHEST makes them IEEE float32 (the GPU tests).
PRECISION: jax.lax.Precision | None = None
INTERPRET: bool | None = None  # Pallas' interpreter; None: off GPUs


# The constants above that `constants` sets (integers; 0/1 for the switches).
TUNABLE = (
    "BLOCK",
    "NUM_WARPS",
    "WGRAD_BLOCK",
    "WGRAD_STEPS",
    "WGRAD_MIN_PROGRAMS",
    "WGRAD_WARPS",
    "WGRAD_G_FIRST",
    "WGRAD_ANCHORS",
    "STAGES",
    "TAP_LOOP",
    "CONV_STAGES",
)


# Constants that must be powers of two (Triton's block shapes, warps) or at least 1; switches 0/1.
_POWERS_OF_TWO = ("BLOCK", "NUM_WARPS", "WGRAD_BLOCK", "WGRAD_STEPS", "WGRAD_WARPS")
_SWITCHES = ("WGRAD_G_FIRST", "WGRAD_ANCHORS", "TAP_LOOP")


def parse_constants(setting: str | dict) -> dict[str, int]:
    """ "NAME=INT,..." ("" for none) or {NAME: INT} -> {NAME: INT}, each NAME one of TUNABLE
    and each value one it can take; otherwise a ValueError naming the item."""
    if isinstance(setting, str):
        items = [part.strip() for part in setting.split(",") if part.strip()]
        pairs = [item.partition("=") for item in items]
    else:
        items = [f"{name}={value}" for name, value in setting.items()]
        pairs = [(name, "=", str(value)) for name, value in setting.items()]
    parsed = {}
    for item, (name, eq, value) in zip(items, pairs):
        name = name.strip()
        if name not in TUNABLE or not eq:
            raise ValueError(
                f"kernel constant {item!r}: give NAME=INT with NAME one of {', '.join(TUNABLE)}"
            )
        try:
            number = int(value)
        except ValueError:
            raise ValueError(
                f"kernel constant {item!r}: {value.strip()!r} is not an integer"
            ) from None
        if name in _SWITCHES and number not in (0, 1):
            raise ValueError(f"kernel constant {item!r}: {name} is a switch, 0 or 1")
        if name in _POWERS_OF_TWO and (number < 1 or number & (number - 1)):
            raise ValueError(f"kernel constant {item!r}: {name} must be a power of two")
        minimum = 1 if name.endswith("STAGES") else 0
        if number < minimum:
            raise ValueError(f"kernel constant {item!r}: {name} must be at least {minimum}")
        parsed[name] = number
    return parsed


@contextlib.contextmanager
def constants(setting: str | dict):
    """This module's constants set as `setting` says ("NAME=INT,..." or a dict: `parse_constants`)
    while the block runs, then restored, also when it raises. They are read as programs are
    traced (a jitted function traced before keeps what it was traced with), and they are the
    process's: programs traced in other threads meanwhile see them too (the trainer traces its
    Pallas stacks in the update only, on the main thread)."""
    setting = parse_constants(setting)
    old = {name: globals()[name] for name in setting}
    try:
        for name, value in setting.items():
            globals()[name] = type(old[name])(value)
        yield
    finally:
        globals().update(old)


def _interpret() -> bool:
    return jax.default_backend() != "gpu" if INTERPRET is None else INTERPRET


def channels_for(n: int) -> int:
    """The channel count the kernels compute n channels with: the next power of two, >= 16."""
    return max(16, 1 << (n - 1).bit_length())


def _pads(pads, n: int) -> tuple[int, ...]:
    return (pads,) * n if isinstance(pads, int) else tuple(pads)


def supported(x, layers, pads, stride: int = 1, shift: int = 0) -> bool:
    """Whether `conv_stack` takes this stack (x: an array or its shape and dtype): square NHWC
    images, square kernels no wider than 3 padded by less than their width, and channel counts
    that are powers of two >= 16 (Triton's dot). A strided first layer reads integer pixels of
    at most 16 channels, unpadded (and only they may be read through a random shift)."""
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
    first = int(stride > 1)  # the pixels of a strided first layer are read as they are
    return (
        all(c >= 16 and c & (c - 1) == 0 for c in channels[first:])
        and [k[2] for k in kernels] == channels[:-1]
        and min(_sizes(x.shape[1], [k[0] for k in kernels], pads, stride)) > 0
    )


def _sizes(size: int, kernels, pads, stride: int = 1) -> list[int]:
    """The side of the input and of each layer's output (kernels: each layer's width)."""
    sizes = [size]
    for i, (k, p) in enumerate(zip(kernels, pads)):
        s = stride if i == 0 else 1
        sizes.append((sizes[-1] + 2 * p - k) // s + 1)
    return sizes


@dataclasses.dataclass(frozen=True)
class _Grid:
    """An activation as the kernels hold it: [rows, C], pixel (y, x) of image n at row
    (n * size + y) * size + x, then zero rows up to a multiple of both blocks: a convolution's
    programs cover the rows exactly, and each step of a filter gradient lies wholly inside
    them or wholly past them (where its masked loads read zeros)."""

    images: int
    size: int

    @property
    def pixels(self) -> int:
        return self.images * self.size * self.size

    @property
    def rows(self) -> int:
        return _round_up(self.pixels, math.lcm(BLOCK, WGRAD_BLOCK))

    def flatten(self, x: jax.Array) -> jax.Array:
        """[N, size, size, C] -> [rows, C]."""
        return jnp.pad(x.reshape(-1, x.shape[-1]), ((0, self.rows - self.pixels), (0, 0)))

    def unflatten(self, flat: jax.Array) -> jax.Array:
        """[rows, C] -> [N, size, size, C]."""
        return flat[: self.pixels].reshape(self.images, self.size, self.size, flat.shape[-1])

    def position(self, rows):
        """(in the pixels, image, y, x) of each row."""
        image, pixel = jax.lax.div(rows, self.size**2), jax.lax.rem(rows, self.size**2)
        y, x = jax.lax.div(pixel, self.size), jax.lax.rem(pixel, self.size)
        return rows < self.pixels, image, y, x


def _traced(t) -> bool:
    """Whether a tap's index is a loop's (traced) rather than a Python int."""
    return not isinstance(t, int)


def _round_up(n: int, multiple: int) -> int:
    return -(-n // multiple) * multiple


def _gather_rows(ref, ok, row, lanes: int) -> jax.Array:
    """[len(row), lanes]: rows `row` of a flat ref of rows of `lanes` values, zeros where not
    `ok` (those rows are not read)."""
    idx = jnp.where(ok, row, 0)[:, None] * lanes + jnp.arange(lanes, dtype=jnp.int32)
    return plt.load(ref.at[idx], mask=jnp.broadcast_to(ok[:, None], idx.shape), other=0)


@dataclasses.dataclass(frozen=True)
class _Pass:
    """One convolution of a stack: k x k taps over the `size_in` x `size_in` input zero-padded
    by `pad`, giving `size` x `size` (VALID, stride 1)."""

    images: int
    size_in: int
    size: int
    kernel: int
    pad: int

    @property
    def out(self) -> _Grid:
        return _Grid(self.images, self.size)

    @property
    def input_gradient(self) -> _Pass:
        """The convolution that computes this one's input gradient (with the kernel flipped
        and transposed, `_taps_of(..., flip=True)`)."""
        return _Pass(self.images, self.size, self.size_in, self.kernel, self.kernel - 1 - self.pad)

    def loader(self, x_ref, rows, c: int, dtype):
        """tap t = (i, j) -> [len(rows), c]: for the output pixel (y, x) at each of `rows`,
        input pixel (y + i - pad, x + j - pad), zero where that is padding or the row is past
        the pixels. x_ref is the input's rows as one dimension."""
        keep, image, y, x = self.out.position(rows)
        base = (image * self.size_in + y - self.pad) * self.size_in + x - self.pad
        lanes = jnp.arange(c, dtype=jnp.int32)[None, :]
        if not self.pad:  # a VALID convolution reads inside its input
            base = jnp.where(keep, base, 0)
        k, last = self.kernel, self.size_in - 1

        def load(t):
            i, j = (jax.lax.div(t, k), jax.lax.rem(t, k)) if _traced(t) else divmod(t, k)
            idx = base + i * self.size_in + j
            if not self.pad:
                return x_ref[idx[:, None] * c + lanes].astype(dtype)
            ok = keep
            # (the checks that can fail for this tap: the output spans [0, size) and
            # size - 1 + k - 1 - 2 * pad = size_in - 1; a traced tap checks all four)
            if _traced(t) or i < self.pad:
                ok &= y + i - self.pad >= 0
            if _traced(t) or i > k - 1 - self.pad:
                ok &= y + i - self.pad <= last
            if _traced(t) or j < self.pad:
                ok &= x + j - self.pad >= 0
            if _traced(t) or j > k - 1 - self.pad:
                ok &= x + j - self.pad <= last
            return _gather_rows(x_ref, ok, idx, c).astype(dtype)

        return load


@dataclasses.dataclass(frozen=True)
class _Pixels:
    """The input of a strided first layer: x itself ([N, side, side, channels]), read for
    each output pixel one kernel row at a time: the `kernel` pixels of row i are kernel *
    channels consecutive values, one load of `width` lanes (a power of two >= 16; the lanes
    past them read zeros)."""

    side: int
    channels: int
    stride: int
    kernel: int
    out: _Grid  # the layer's output
    shift: int = 0  # the pad of a random shift read with the pixels (augment.shift); 0: none

    @property
    def width(self) -> int:
        return channels_for(self.kernel * self.channels)

    def loader(self, x_ref, crop_ref, rows, dtype):
        """kernel row i -> [len(rows), width]: for each output pixel at `rows`, its input
        pixels of that row (zeros past the pixels). With a shift, the pixels of each image's
        crop at its (dy, dx) in crop_ref (flat [N * 2]): pixel (Y, X) of the crop is pixel
        (clip(Y + dy - shift), clip(X + dx - shift)) of the image, as `augment.shift` crops
        the edge-padded image."""
        keep, image, y, x = self.out.position(rows)
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
        dy, dx = _crop_offsets(crop_ref, image, keep)
        last = self.side - 1
        # lane l holds channel l % C of the row's pixel l // C
        pixel, channel = jax.lax.div(lanes, self.channels), jax.lax.rem(lanes, self.channels)
        col = self.stride * x + dx - self.shift
        col = jnp.clip(col[:, None] + pixel[None, :], 0, last)
        # Each lane's offset within an image row, the same for every kernel row: a kernel row's
        # indices are then one addition per lane (the forward kernel kept 58% of the SM's issue
        # slots busy: index arithmetic; benchmarks/results/kernels/counters_dear_1seed_h200.json).
        lane_offset = col * self.channels + channel[None, :]

        def load(i):
            row = jnp.clip(self.stride * y + i + dy - self.shift, 0, last)
            start = (image * self.side + row) * (self.side * self.channels)
            idx = start[:, None] + lane_offset
            return plt.load(x_ref.at[idx], mask=mask, other=0).astype(dtype)

        return load


def _crop_offsets(crop_ref, image, keep):
    """(dy, dx): the random-shift offsets of each row's image, from crop_ref (flat [N * 2]);
    `image` must be a valid index (0) where `keep` is False."""
    return tuple(plt.load(crop_ref.at[2 * image + axis], mask=keep, other=0) for axis in (0, 1))


@dataclasses.dataclass(frozen=True)
class _Targets:
    """The targets of a last layer's loss (`LOSSES`), for a layer that computes `phase` x
    `phase` output pixels per row (its output phases): lane (ry * phase + rx) * channels + c of
    the row of output (n, i, j) is channel c of pixel (phase * i + ry, phase * j + rx) of image
    n of the targets ([N, side, side, channels] of any numeric dtype). They may be read through
    a random shift (as `_Pixels`)."""

    side: int
    channels: int
    phase: int
    out: _Grid  # the last layer's output
    shift: int = 0
    loss: str = "bce"

    @property
    def lanes(self) -> int:
        return self.phase**2 * self.channels

    def load(self, y_ref, crop_ref, rows, f: int):
        """([len(rows), f] float32 targets of the output at `rows`, where they are defined: the
        pixels' rows and the first `lanes` lanes)."""
        keep, image, i, j = self.out.position(rows)
        image = jnp.where(keep, image, 0)
        lanes = jnp.arange(f, dtype=jnp.int32)
        ok = keep[:, None] & (lanes < self.lanes)[None, :]
        pixel, channel = jax.lax.div(lanes, self.channels), jax.lax.rem(lanes, self.channels)
        row = self.phase * i[:, None] + jax.lax.div(pixel, self.phase)[None, :]
        col = self.phase * j[:, None] + jax.lax.rem(pixel, self.phase)[None, :]
        if self.shift:
            last = self.side - 1
            dy, dx = _crop_offsets(crop_ref, image, keep)
            row = jnp.clip(row + dy[:, None] - self.shift, 0, last)
            col = jnp.clip(col + dx[:, None] - self.shift, 0, last)
        idx = ((image[:, None] * self.side + row) * self.side + col) * self.channels
        idx = jnp.where(ok, idx + channel[None, :], 0)
        return plt.load(y_ref.at[idx], mask=ok, other=0).astype(jnp.float32), ok


def _loader(x_ref, crop_ref, rows, layer, c: int, dtype):
    """tap t -> the input of `layer` (a `_Pass` or `_Pixels`) for the output pixels at `rows`,
    [len(rows), c] in `dtype`."""
    if isinstance(layer, _Pixels):
        return layer.loader(x_ref, crop_ref, rows, dtype)
    return layer.loader(x_ref, rows, c, dtype)


def _conv_kernel(*refs, layer, relu, has_bias, has_mask, targets):
    x_ref, *refs = refs
    loss_ref = refs.pop() if targets is not None else None
    o_ref = refs.pop()
    crop_ref = refs.pop(0) if isinstance(layer, _Pixels) and layer.shift else None
    w_ref = refs.pop(0)
    b_ref = refs.pop(0) if has_bias else None
    m_ref = refs.pop(0) if has_mask else None
    f, c = o_ref.shape[-1], w_ref.shape[1]
    start = pl.program_id(0) * BLOCK
    rows = start + jnp.arange(BLOCK, dtype=jnp.int32)
    taps = _loader(x_ref, crop_ref, rows, layer, c, w_ref.dtype)

    def tap(t, acc):
        return acc + plt.dot(taps(t), w_ref[t], precision=PRECISION)

    acc = jnp.zeros((BLOCK, f), jnp.float32)
    if TAP_LOOP:
        acc = jax.lax.fori_loop(0, w_ref.shape[0], tap, acc)
    else:
        for t in range(w_ref.shape[0]):
            acc = tap(t, acc)
    if has_bias:
        acc += b_ref[...][None, :]
    if relu:
        acc = jnp.maximum(acc, 0.0)
    keep = (rows < layer.out.pixels)[:, None]
    if has_mask:
        keep &= m_ref[pl.ds(start, BLOCK), :] > 0
    if targets is not None:
        y_ref = refs.pop(0)
        target_crop_ref = refs.pop(0) if targets.shift else None
        y, keep = targets.load(y_ref, target_crop_ref, rows, f)
        acc, loss = LOSSES[targets.loss](acc, y)
        loss_ref[pl.program_id(0)] = jnp.sum(jnp.where(keep, loss, 0.0), axis=0)
    o_ref[pl.ds(start, BLOCK), :] = jnp.where(keep, acc, 0.0).astype(o_ref.dtype)


def _bce(logits, y):
    """(the gradient for the logits, sigmoid(logits) - y; BCE(sigmoid(logits), y) =
    softplus(logits) - logits * y), float32, elementwise, for {0, 1} labels y, with
    exp(-|logits|) the only exponential (no overflow). `losses.sigmoid_cross_entropy`."""
    e = jnp.exp(-jnp.abs(logits))
    sigmoid = jnp.where(logits >= 0, 1.0, e) / (1.0 + e)
    return sigmoid - y, jnp.maximum(logits, 0.0) + jnp.log1p(e) - logits * y


def _clipped_squares(out, y):
    """(the gradient for the output, the squared error (clip(out, -0.5, 0.5) - (y / 255 -
    0.5))^2), float32, elementwise, for pixels y in [0, 255]: `losses.reconstruction_loss`
    summed. The clip passes the gradient strictly inside (-0.5, 0.5) (autodiff of `jnp.clip`
    passes half of it at exactly +-0.5)."""
    err = jnp.clip(out, -0.5, 0.5) - (y / 255.0 - 0.5)
    inside = (out > -0.5) & (out < 0.5)
    return jnp.where(inside, 2.0 * err, 0.0), err * err


# The losses a last layer's kernel computes with its output: name -> (out, target) ->
# (the loss's gradient for out, the loss), elementwise.
LOSSES = {"bce": _bce, "clipped_squares": _clipped_squares}


def _conv(x, w, layer, *, bias=None, relu=False, mask=None, targets=None):
    """The rows of layer.out: out[q] = sum_t (tap t of x for q) @ w[t] (+ bias, ReLU) in w's
    dtype, zero where `mask` (of the same rows) is not positive (if given) and past the
    pixels. x may be of another dtype (uint8 pixels): each tap is converted to w's. For a
    `_Pixels` layer x is its input as it is (with a shift, x is (pixels, crop offsets)).

    With `targets` = (a `_Targets`, its arguments: the targets, and with a shift their crop
    offsets), the output is instead the gradient of its loss for that output (zero where no
    target is defined), returned with each program's per-lane sums of the loss."""
    args = [*_pixel_args(x, layer), w]
    if bias is not None:
        args.append(bias.astype(jnp.float32))
    if mask is not None:
        args.append(mask)
    target, target_args = targets if targets is not None else (None, ())
    args.extend(target_args)
    rows, f = layer.out.rows, w.shape[-1]
    out_shape = jax.ShapeDtypeStruct((rows, f), w.dtype)
    if target is not None:
        out_shape = (out_shape, jax.ShapeDtypeStruct((rows // BLOCK, f), jnp.float32))
    return pl.pallas_call(
        functools.partial(
            _conv_kernel,
            layer=layer,
            relu=relu,
            has_bias=bias is not None,
            has_mask=mask is not None,
            targets=target,
        ),
        out_shape=out_shape,
        grid=(rows // BLOCK,),
        interpret=_interpret(),
        # Triton's parameters also pick Pallas' Triton backend (not Mosaic GPU).
        compiler_params=plt.CompilerParams(num_warps=NUM_WARPS, num_stages=CONV_STAGES),
    )(*args)


@dataclasses.dataclass(frozen=True)
class _Anchors:
    """The rows a filter gradient steps over with `WGRAD_ANCHORS`, for a `_Pass` of k x k taps
    with pad p and output side s: anchor (n, Y, X), Y < s + k - 1, X < s, pairs the output
    gradient's pixel (n, Y - i, X) (where 0 <= Y - i < s) with the input's pixel
    (n, Y - p, X + j - p) (zero in the padding) for every tap (i, j). Output pixel (y, x) meets
    tap (i, j) at one anchor only, (y + i, x), so the sum over anchors of x_j^T g_i is tap
    (i, j)'s filter gradient, and a step reads k blocks of each operand where one over output
    rows reads k * k of the input and one of the gradient: (s + k - 1) / s as many rows, 2k
    loads instead of k * k + 1."""

    layer: _Pass

    @property
    def rows(self) -> int:
        return self.layer.images * (self.layer.size + self.layer.kernel - 1) * self.layer.size

    def load(self, x_ref, g_ref, rows, c: int, f: int, dtype):
        """([x_j for each j], [g_i for each i]) at the anchors `rows` (past the anchors: zeros);
        x_ref and g_ref flat, the input's and the output gradient's rows (`_Grid`)."""
        k, p, s, side = self.layer.kernel, self.layer.pad, self.layer.size, self.layer.size_in
        keep = rows < self.rows
        tall = s + k - 1
        image, rest = jax.lax.div(rows, tall * s), jax.lax.rem(rows, tall * s)
        y, x = jax.lax.div(rest, s), jax.lax.rem(rest, s)

        xs = []
        for j in range(k):
            ok = keep  # a VALID layer's anchors read inside its input
            if p:
                ok = ok & (y >= p) & (y - p < side) & (x + j >= p) & (x + j - p < side)
            row = (image * side + y - p) * side + x + j - p
            xs.append(_gather_rows(x_ref, ok, row, c).astype(dtype))
        gs = [
            _gather_rows(g_ref, keep & (y >= i) & (y - i < s), (image * s + y - i) * s + x, f)
            for i in range(k)
        ]
        return xs, gs


def _anchors(layer) -> _Anchors | None:
    """The anchors a filter gradient of `layer` steps over, None: its output rows."""
    use = WGRAD_ANCHORS and isinstance(layer, _Pass) and layer.kernel > 1
    return _Anchors(layer) if use else None


def _wgrad_kernel(*refs, layer, steps, anchors):
    x_ref, *refs, w_ref, b_ref = refs
    crop_ref = refs.pop(0) if isinstance(layer, _Pixels) and layer.shift else None
    g_ref = refs.pop(0)
    n, *acc_shape = w_ref.shape[1:]  # taps, then [c, f] ([f, c] with WGRAD_G_FIRST)
    f = b_ref.shape[-1]
    c = acc_shape[1] if WGRAD_G_FIRST else acc_shape[0]
    p = pl.program_id(0)

    def product(x, g):
        if WGRAD_G_FIRST:
            return plt.dot(g, x, trans_a=True, precision=PRECISION)
        return plt.dot(x, g, trans_a=True, precision=PRECISION)

    def step(s, carry):
        accs, bacc = carry
        start = (p * steps + s) * WGRAD_BLOCK
        rows = start + jnp.arange(WGRAD_BLOCK, dtype=jnp.int32)
        if anchors is not None:
            xs, gs = anchors.load(x_ref, g_ref, rows, c, f, g_ref.dtype)
            k = len(xs)
            out = tuple(acc + product(xs[t % k], gs[t // k]) for t, acc in enumerate(accs))
            return out, bacc + jnp.sum(gs[0].astype(jnp.float32), axis=0)
        # The last program's steps past the rows read zeros (whole blocks: see _Grid).
        inside = jnp.broadcast_to((rows < layer.out.rows)[:, None], (WGRAD_BLOCK, f))
        g = plt.load(g_ref.at[pl.ds(start, WGRAD_BLOCK), :], mask=inside, other=0)
        taps = _loader(x_ref, crop_ref, rows, layer, c, g.dtype)
        out = tuple(acc + product(taps(t), g) for t, acc in enumerate(accs))
        return out, bacc + jnp.sum(g.astype(jnp.float32), axis=0)

    zeros = tuple(jnp.zeros(acc_shape, jnp.float32) for _ in range(n))
    accs, bacc = jax.lax.fori_loop(0, steps, step, (zeros, jnp.zeros((f,), jnp.float32)))
    for t in range(n):
        w_ref[p, t] = accs[t]
    b_ref[p] = bacc


def _pixel_args(x, layer) -> list:
    """A layer's input as the kernels take it: flat, and with a shift its crop offsets."""
    if isinstance(layer, _Pixels) and layer.shift:
        return [x[0].reshape(-1), x[1].reshape(-1).astype(jnp.int32)]
    return [x.reshape(-1)]


def _wgrad_steps(rows: int, batch: int) -> int:
    """Steps per program of a filter gradient over `rows` output rows, for `batch` vmapped
    copies of it (WGRAD_MIN_PROGRAMS)."""
    steps, target = WGRAD_STEPS, 0 if _interpret() else WGRAD_MIN_PROGRAMS
    while steps > 1 and batch * -(-rows // (WGRAD_BLOCK * steps)) < target:
        steps //= 2
    return steps


def _wgrad(x, g, layer):
    """(sum_q (tap t of x for q)^T g[q] for each t, sum_q g[q]) over the rows of layer.out,
    in float32."""
    c = layer.width if isinstance(layer, _Pixels) else x.shape[-1]
    return _wgrad_over(layer, c, ())(*_pixel_args(x, layer), g)


def _wgrad_over(layer, c: int, axes: tuple[int, ...]):
    """`_wgrad` of the flat arguments, each with leading axes of these sizes (the vmapped axes
    met so far, outermost first), so that the kernel's steps follow the size of its whole grid.
    Under a further jax.vmap it becomes the same with that axis in front."""

    @jax.custom_batching.custom_vmap
    def wgrad(*args):
        steps = _wgrad_steps(_wgrad_rows(layer), math.prod(axes))
        fn = functools.partial(_wgrad_call, layer, c, steps)
        for _ in axes:
            fn = jax.vmap(fn)
        return fn(*args)

    @wgrad.def_vmap
    def _rule(axis_size, in_batched, *args):
        args = [
            a if b else jnp.broadcast_to(a, (axis_size, *a.shape)) for a, b in zip(args, in_batched)
        ]
        return _wgrad_over(layer, c, (axis_size, *axes))(*args), (True, True)

    return wgrad


def _wgrad_rows(layer) -> int:
    """How many rows a filter gradient of `layer` steps over."""
    anchors = _anchors(layer)
    return layer.out.rows if anchors is None else anchors.rows


def _wgrad_call(layer, c: int, steps: int, *args):
    f = args[-1].shape[-1]
    taps = layer.kernel if isinstance(layer, _Pixels) else layer.kernel**2
    anchors = _anchors(layer)
    if anchors is not None:  # the output gradient gathered too
        args = (*args[:-1], args[-1].reshape(*args[-1].shape[:-2], -1))
    programs = -(-_wgrad_rows(layer) // (WGRAD_BLOCK * steps))
    acc_shape = (f, c) if WGRAD_G_FIRST else (c, f)
    w, b = pl.pallas_call(
        functools.partial(_wgrad_kernel, layer=layer, steps=steps, anchors=anchors),
        out_shape=(
            jax.ShapeDtypeStruct((programs, taps, *acc_shape), jnp.float32),
            jax.ShapeDtypeStruct((programs, f), jnp.float32),
        ),
        grid=(programs,),
        interpret=_interpret(),
        compiler_params=plt.CompilerParams(num_warps=WGRAD_WARPS, num_stages=STAGES),
    )(*args)
    w = w.sum(0)
    return (jnp.swapaxes(w, 1, 2) if WGRAD_G_FIRST else w), b.sum(0)


def _plan(x_shape, layers, pads, stride, shift=0) -> tuple[list[int], list]:
    """(the sides of the input and of each layer's output, each layer's `_Pass`, the first a
    `_Pixels` if strided)."""
    kernels = [k.shape[0] for k, _ in layers]
    sizes = _sizes(x_shape[1], kernels, pads, stride)
    n = x_shape[0]
    passes = [_Pass(n, sizes[i], sizes[i + 1], k, p) for i, (k, p) in enumerate(zip(kernels, pads))]
    if stride > 1:
        passes[0] = _Pixels(x_shape[1], x_shape[-1], stride, kernels[0], _Grid(n, sizes[1]), shift)
    return sizes, passes


def _taps_of(k: jax.Array, layer, flip: bool = False) -> jax.Array:
    """[K, K, C, F] -> one [C, F] matrix per tap (i, j), in the order i * K + j; flipped and
    transposed for an input gradient ([F, C] at tap (K-1-i, K-1-j)); for a `_Pixels` layer, one
    [layer.width, F] matrix per kernel row (its K * C rows, then zeros)."""
    if isinstance(layer, _Pixels):
        k = k.reshape(k.shape[0], -1, k.shape[-1])
        return jnp.pad(k, ((0, 0), (0, layer.width - k.shape[1]), (0, 0)))
    if flip:
        k = jnp.swapaxes(jnp.flip(k, (0, 1)), 2, 3)
    return k.reshape(-1, *k.shape[2:])


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


def _forward(x, layers, pads, relu_last, dtype, stride, shift, crops, targets=None):
    """(the stack's output, the activations: its input as the kernels read it, then each
    layer's output). With `targets` (see `_conv`), the last layer's output is instead its
    loss's gradient and each program's sums, and the activations end at that layer's input."""
    dtype = dtype or x.dtype
    pads = _pads(pads, len(layers))
    sizes, passes = _plan(x.shape, layers, pads, stride, shift)
    if stride > 1:  # pixels read as they are (through the crops, with a shift)
        acts = [(x, crops) if shift else x]
    else:
        acts = [_Grid(x.shape[0], sizes[0]).flatten(x)]
    for i, ((k, b), layer) in enumerate(zip(layers, passes)):
        w = _taps_of(k, layer).astype(dtype)
        last = i == len(layers) - 1
        if last and targets is not None:
            return _conv(acts[-1], w, layer, bias=b, targets=targets), acts
        acts.append(_conv(acts[-1], w, layer, bias=b, relu=relu_last or not last))
    return passes[-1].out.unflatten(acts[-1]), acts


def _like(x) -> jax.Array:
    """An empty array that keeps x's shape (all but its last axis of size 0) and dtype: what the
    backward pass's plan and its input gradient need of x."""
    return jnp.zeros((*x.shape, 0), x.dtype)


def _conv_stack_fwd(x, layers, pads, relu_last, dtype, stride, shift, crops):
    y, acts = _forward(x, layers, pads, relu_last, dtype, stride, shift, crops)
    return y, (acts, layers, _like(x))


def _conv_stack_bwd(pads, relu_last, dtype, stride, shift, residuals, g):
    acts, layers, x_like = residuals
    pads = _pads(pads, len(layers))
    _, passes = _plan(x_like.shape[:-1], layers, pads, stride, shift)
    # The gradient at the last layer's output (its pre-activations, after a ReLU).
    g = passes[-1].out.flatten(g.astype(acts[-1].dtype))
    if relu_last:
        g = jnp.where(acts[-1] > 0, g, 0)
    dx, grads = _backward(acts, layers, passes, g, x_like)
    return dx, grads, None


def _backward(acts, layers, passes, g, x_like, scale=None):
    """(the input's gradient, None for integers; each layer's (kernel, bias) gradients) from g,
    the gradient at the last layer's pre-activations as rows, times `scale` if given (a scalar:
    applied to the last layer's filter gradients and folded into the weights of its input
    gradient, whose result carries it down the stack)."""
    grads = []
    for i in reversed(range(len(layers))):
        (k, b), layer = layers[i], passes[i]
        dk, db = _wgrad(acts[i], g, layer)
        w = _taps_of(k, layer, flip=True)
        if scale is not None and i == len(layers) - 1:
            dk, db, w = dk * scale, db * scale, w * scale
        dk = dk[:, : k.shape[1] * k.shape[2]] if isinstance(layer, _Pixels) else dk
        grads.append((dk.reshape(k.shape).astype(k.dtype), db.astype(b.dtype)))
        if i == 0 and not jnp.issubdtype(x_like.dtype, jnp.floating):
            return None, tuple(reversed(grads))
        # Input gradient, with the ReLU gradient of the layer below (the stack's input has none).
        g = _conv(g, w.astype(g.dtype), layer.input_gradient, mask=acts[i] if i else None)
    dx = passes[0].input_gradient.out.unflatten(g).astype(x_like.dtype)
    return dx, tuple(reversed(grads))


conv_stack.defvjp(_conv_stack_fwd, _conv_stack_bwd)


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4, 5, 6, 8))
def conv_stack_loss(
    x, layers, targets, pads, dtype=None, phase=1, shift=0, crops=None, loss="bce"
) -> jax.Array:
    """A loss of a stack's output (`conv_stack` with no ReLU after the last layer) against
    `targets`, summed over every image, pixel and channel: a scalar. `loss` (`LOSSES`):
    - "bce": the binary cross-entropy of the output as logits (`losses.sigmoid_cross_entropy`)
      against {0, 1} labels (uint8 masks, bool or float);
    - "clipped_squares": (clip(output, -0.5, 0.5) - (pixels / 255 - 0.5))^2 against integer
      pixels (`losses.reconstruction_loss`).

    The last layer's kernel computes the loss and its gradient as it computes the output, which
    is never written: its output rows are the gradient, and no pass of XLA reads or writes
    the output. The loss is taken of the float32 output.

    targets: [N, S, S, C] with S = phase * H', where H' is the last layer's output side; the
    output's first phase**2 * C channels are their pixels as `networks.space_to_depth(targets,
    phase)` lays them out (the rest get no loss). They may be read through a random shift:
    `augment.shift` with pad `shift` > 0 at each image's offsets in `crops` [N, 2]. Targets
    and crops get no gradient. x, layers, pads, dtype: as `conv_stack` (stride 1).
    """
    return _loss_forward(x, layers, targets, pads, dtype, phase, shift, crops, loss)[0]


def _loss_forward(x, layers, targets, pads, dtype, phase, shift, crops, loss):
    if loss not in LOSSES:
        raise ValueError(f"unknown loss {loss!r}; valid: {sorted(LOSSES)}")
    pads = _pads(pads, len(layers))
    _, passes = _plan(x.shape, layers, pads, 1)
    out, f = passes[-1].out, layers[-1][0].shape[-1]
    n, side, width, channels = targets.shape
    side_ok = side == width == phase * out.size
    if n != out.images or not side_ok or phase**2 * channels > f:
        raise ValueError(
            f"targets {targets.shape} do not match the stack's output: {out.images} images of "
            f"{out.size} x {out.size} x {f}, {phase} x {phase} phases per pixel"
        )
    if shift and (crops is None or crops.shape != (n, 2)):
        shape = None if crops is None else crops.shape
        raise ValueError(f"a shift needs crop offsets of shape {(n, 2)}, got {shape}")
    if targets.dtype == jnp.bool_:
        targets = targets.astype(jnp.uint8)
    spec = _Targets(side, channels, phase, out, shift, loss)
    args = [targets.reshape(-1)]
    if shift:
        args.append(crops.reshape(-1).astype(jnp.int32))
    (grad, sums), acts = _forward(x, layers, pads, False, dtype, 1, 0, None, (spec, args))
    return jnp.sum(sums), (acts, grad, layers, _like(x))


def _conv_stack_loss_bwd(pads, dtype, phase, shift, loss, residuals, g):
    acts, grad, layers, x_like = residuals
    _, passes = _plan(x_like.shape[:-1], layers, _pads(pads, len(layers)), 1)
    dx, grads = _backward(acts, layers, passes, grad, x_like, scale=g)
    return dx, grads, None, None


conv_stack_loss.defvjp(_loss_forward, _conv_stack_loss_bwd)
