"""Flax modules of DrQ-v2 and the auxiliary heads of DEAR, SEAR and TED (docs/method.md, Architecture).

Every module works on one unbatched-or-batched array with channels last; seeds are added by
`jax.vmap` at the call site, never here. Initialisation follows DrQ-v2: orthogonal weights (gain 1
for linear layers, sqrt(2) for convolutions and transposed convolutions), zero biases, drawn as
PyTorch's `nn.init.orthogonal_` draws them on its own weight layouts.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
import math
from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from dear_jax import augment, losses, wgrad, wideconv

LINEAR_INIT = nn.initializers.orthogonal(1.0)
# A conv kernel [kh, kw, in, out] flattened to [kh*kw*in, out] is the transpose of PyTorch's
# [out, in*kh*kw] up to a permutation of rows, so Flax's orthogonal init has PyTorch's law.
CONV_INIT = nn.initializers.orthogonal(math.sqrt(2.0))
ZEROS = nn.initializers.zeros


def conv_transpose_init(key, shape, dtype=jnp.float32):
    """`nn.init.orthogonal_(w, sqrt(2))` on PyTorch's ConvTranspose2d layout, as our kernel.

    PyTorch flattens a transposed-convolution weight [in, out, kh, kw] to [in, out*kh*kw] and
    makes that orthogonal; Flax's init on our [kh, kw, in, out] kernel would make
    [kh*kw*in, out] orthogonal instead, a different scale whenever in != out.
    """
    kh, kw, cin, cout = shape
    w = nn.initializers.orthogonal(math.sqrt(2.0))(key, (cin, cout * kh * kw), dtype)
    return w.reshape(cin, cout, kh, kw).transpose(2, 3, 0, 1)


def _dense(features: int, name: str | None = None, dtype=jnp.float32, products=None) -> nn.Dense:
    """A Linear layer computing in `dtype`; with `products` of another dtype (bf16), a layer
    whose matrix product reads its operands in that dtype (`mixed_dot_general`)."""
    mixed = products is not None and jnp.dtype(products) != jnp.dtype(dtype)
    dot = mixed_dot_general(products) if mixed else None
    return nn.Dense(
        features, kernel_init=LINEAR_INIT, bias_init=ZEROS, name=name, dtype=dtype, dot_general=dot
    )


def mixed_dot_general(dtype):
    """A Linear layer's lax.dot_general on operands rounded to `dtype`, accumulated and returned
    in float32: the actor's and the critic's products in the bf16 path. Their activations,
    LayerNorm, biases and outputs stay float32; the gradient's two products also read `dtype`
    operands (the float32 cotangent rounded) into float32 results (`_mixed_dot`). On an H100
    the forward products in bf16 took the 5-seed DEAR update from 2.96 to 2.91 ms per seed, on
    one machine; DrQ-v2's (plain encoder, 39200-wide trunk) measured 1.93 against 2.14 on other
    machines; the gradient's in bf16 then took DEAR from 2.43 to 2.38 on an H200
    (benchmarks/RESULTS.md)."""

    def dot_general(lhs, rhs, dimension_numbers, precision=None, preferred_element_type=None):
        del precision, preferred_element_type  # float32 accumulation and result
        (contract, batch) = dimension_numbers
        if tuple(map(tuple, contract)) != ((lhs.ndim - 1,), (0,)) or rhs.ndim != 2 or batch[0]:
            raise ValueError(f"a Linear layer's product, not {dimension_numbers}")
        return _mixed_dot(lhs, rhs, jnp.dtype(dtype))

    return dot_general


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def _mixed_dot(x: jax.Array, w: jax.Array, dtype) -> jax.Array:
    """x [..., K] @ w [K, N] on operands rounded to `dtype`, in float32. Its gradient's products
    read `dtype` operands too: by JAX's own rule they would read the float32 cotangent, which
    makes XLA promote the other operand and run both in float32 (TF32 on GPUs)."""
    return jnp.matmul(x.astype(dtype), w.astype(dtype), preferred_element_type=jnp.float32)


def _mixed_dot_fwd(x, w, dtype):
    return _mixed_dot(x, w, dtype), (x, w)


def _mixed_dot_bwd(dtype, residuals, g):
    x, w = residuals
    x16, w16, g16 = x.astype(dtype), w.astype(dtype), g.astype(dtype)
    dx = jnp.matmul(g16, w16.T, preferred_element_type=jnp.float32)
    rows = tuple(range(x.ndim - 1))  # every axis but the features: summed over for dw
    dw = jax.lax.dot_general(x16, g16, ((rows, rows), ((), ())), preferred_element_type=jnp.float32)
    return dx.astype(x.dtype), dw.astype(w.dtype)


_mixed_dot.defvjp(_mixed_dot_fwd, _mixed_dot_bwd)


def tensor_core_channels(dtype) -> int:
    """Channel multiple the convolutions compute with: 8 for bf16 on GPUs, 1 otherwise.

    cuDNN's bf16 tensor-core convolutions need channel counts that are multiples of 8. With 9
    input channels (3 stacked RGB frames) the first encoder convolution fell back to a generic
    kernel (0.27 ms of a 6 ms bf16 DEAR update at batch 512 on an H100) and its filter gradient
    padded its input on every call (benchmarks/results/profile_dear_bf16_h100.json). Zero
    channels added at use time keep the parameters and the function as they are. On an H100
    (benchmarks/results/encoder_input_h100.json, the conv trunk on obs and next_obs at batch
    512) this took the bf16 trunk from 2.05 to 1.78 ms; in float32 the unpadded path was the
    fastest (3.88 ms against 4.01), so float32 keeps it.
    """
    return 8 if jnp.dtype(dtype) == jnp.bfloat16 and jax.default_backend() == "gpu" else 1


def _pad_axis(x: jax.Array, axis: int, multiple: int) -> jax.Array:
    """`x` with zeros appended along `axis` up to a multiple of `multiple`."""
    extra = -x.shape[axis] % multiple
    if not extra:
        return x
    widths = [(0, 0)] * x.ndim
    widths[axis] = (0, extra)
    return jnp.pad(x, widths)


def _conv2d(x: jax.Array, kernel: jax.Array, stride: int, dtype, channels: int) -> jax.Array:
    """VALID NHWC convolution of [..., H, W, C] with a [kh, kw, C, F] kernel, in `dtype`.

    Input and output channels are zero-padded to a multiple of `channels` for the convolution
    itself (padded outputs are sliced off), which leaves the result unchanged.
    """
    features = kernel.shape[-1]
    lead = x.shape[:-3]
    x = _pad_axis(x.astype(dtype).reshape(-1, *x.shape[-3:]), -1, channels)
    kernel = _pad_axis(_pad_axis(kernel.astype(dtype), 2, channels), 3, channels)
    settings = _CONV.get()
    if settings == ConvSettings():
        y = _plain_conv(x, kernel, stride)
    else:
        y = _custom_conv(x, kernel, stride, settings)
    return y[..., :features].reshape(*lead, *y.shape[-3:-1], features)


def _plain_conv(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
    return jax.lax.conv_general_dilated(
        x, kernel, (stride, stride), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC")
    )


@dataclasses.dataclass(frozen=True)
class ConvSettings:
    """How the networks' convolutions are computed (the same function either way).

    loop_seeds: under `jax.vmap`, each convolution (forward and both gradients) runs once per
        vmapped index, ungrouped. vmap alone turns a convolution whose weights differ per index
        into one grouped convolution (its filter gradient a batch-grouped one), which cuDNN runs
        far slower than separate ones (benchmarks/results/update_h100.json). Everything else
        stays batched (`update.over_seeds(..., "hybrid")`).
    filter_gradient: "cudnn" (XLA's convolution) or "pallas" (`dear_jax.wgrad`, one kernel,
        also for all vmapped seeds at once) where it takes the shape; meant for GPUs: elsewhere
        it runs in Pallas' interpreter.
    stack: how the conv trunk and the decoders' layers after their first run: "auto"
        (`stack_for`: "pallas" on GPUs, "xla" elsewhere), "xla" (one
        convolution each, as above) or "pallas" (`dear_jax.wideconv`: each as one stack of
        Pallas kernels on rows of pixels, one launch per layer for all vmapped seeds, bias,
        ReLU and its gradient fused, the trunk reading the uint8 frames through their crops);
        meant for GPUs: elsewhere it runs in Pallas' interpreter.
    """

    loop_seeds: bool = False
    filter_gradient: str = "cudnn"
    stack: str = "xla"


FILTER_GRADIENTS = ("cudnn", "pallas")
STACKS = ("auto", "xla", "pallas")


def stack_for(name: str) -> str:
    """A conv stack setting as the networks run it: "auto" is "pallas" on GPUs and "xla"
    elsewhere (where Pallas kernels would run in its interpreter)."""
    if name not in STACKS:
        raise ValueError(f"unknown conv stack {name!r}; valid: {STACKS}")
    if name == "auto":
        return "pallas" if jax.default_backend() == "gpu" else "xla"
    return name


# Read at trace time by every convolution of the networks; set by `conv_settings`.
_CONV = contextvars.ContextVar("conv_settings", default=ConvSettings())  # noqa: B039 (frozen)


@contextlib.contextmanager
def conv_settings(**changes):
    """Within it (while tracing), the networks' convolutions follow `ConvSettings(**changes)`
    (fields not named keep their current values)."""
    settings = dataclasses.replace(_CONV.get(), **changes)
    if settings.filter_gradient not in FILTER_GRADIENTS:
        raise ValueError(
            f"unknown filter_gradient {settings.filter_gradient!r}; valid: {FILTER_GRADIENTS}"
        )
    settings = dataclasses.replace(settings, stack=stack_for(settings.stack))
    token = _CONV.set(settings)
    try:
        yield
    finally:
        _CONV.reset(token)


def _unrolled_under_vmap(fn):
    """`fn` of arrays, whose `jax.vmap` calls `fn` once per index and stacks the results."""
    wrapped = jax.custom_batching.custom_vmap(fn)

    @wrapped.def_vmap
    def _rule(axis_size, in_batched, *args):
        outs = [
            fn(*(a[i] if batched else a for a, batched in zip(args, in_batched)))
            for i in range(axis_size)
        ]
        out = jax.tree.map(lambda *xs: jnp.stack(xs), *outs)
        return out, jax.tree.map(lambda _: True, out)

    return wrapped


@functools.cache
def _conv_parts(stride: int, settings: ConvSettings):
    """(forward, input gradient, filter gradient) of a VALID NHWC convolution."""
    forward = functools.partial(_plain_conv, stride=stride)

    def input_grad(x, kernel, g):
        return jax.vjp(lambda x: forward(x, kernel), x)[1](g)[0]

    def cudnn_filter_grad(x, kernel, g):
        return jax.vjp(lambda w: forward(x, w), kernel)[1](g)[0]

    each = _unrolled_under_vmap if settings.loop_seeds else (lambda fn: fn)
    cudnn_filter_grad = each(cudnn_filter_grad)

    def filter_grad(x, kernel, g):
        # Decided per shape (under vmap these are one index's shapes); the Pallas kernel
        # batches itself under vmap, one launch for every index.
        if settings.filter_gradient == "pallas" and wgrad.supported(x.shape, kernel.shape, stride):
            return wgrad.filter_gradient(x, g, kernel.shape[0]).astype(kernel.dtype)
        return cudnn_filter_grad(x, kernel, g)

    return each(forward), each(input_grad), filter_grad


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def _custom_conv(x, kernel, stride: int, settings: ConvSettings) -> jax.Array:
    return _conv_parts(stride, settings)[0](x, kernel)


def _custom_conv_fwd(x, kernel, stride, settings):
    return _custom_conv(x, kernel, stride, settings), (x, kernel)


def _custom_conv_bwd(stride, settings, residuals, g):
    _, input_grad, filter_grad = _conv_parts(stride, settings)
    return input_grad(*residuals, g), filter_grad(*residuals, g)


_custom_conv.defvjp(_custom_conv_fwd, _custom_conv_bwd)


class Conv(nn.Module):
    """`nn.Conv(features, (3, 3), strides, padding="VALID")` with DrQ-v2's init: the same
    parameters (kernel [3, 3, in, out], bias), computed by `_conv2d` (tensor-core channels)."""

    features: int
    stride: int = 1
    dtype: Any = jnp.float32
    channels: int | None = None  # channel multiple; None: tensor_core_channels(dtype)

    @nn.compact
    def __call__(self, x: jax.Array, weights_only: bool = False):
        """The layer of x; with `weights_only`, its (kernel, bias) for an input shaped like x."""
        kernel = self.param("kernel", CONV_INIT, (3, 3, x.shape[-1], self.features))
        bias = self.param("bias", ZEROS, (self.features,))
        if weights_only:
            return kernel, bias
        channels = self.channels or tensor_core_channels(self.dtype)
        return _conv2d(x, kernel, self.stride, self.dtype, channels) + bias.astype(self.dtype)


class ConvTranspose(nn.Module):
    """PyTorch's ConvTranspose2d(k, stride, output_padding), no padding: size (n-1)*s + k + op.

    The same function as `lax.conv_transpose(x, kernel, (s, s), ((k-1, k-1+op),) * 2)`, computed
    as a dense convolution per output phase ("sub-pixel" form): output pixel s*m + r only ever
    meets kernel taps k-1-r, k-1-r-s, ..., so the s*s phases are one VALID convolution of the
    zero-padded input with s*s*features output channels, then interleaved (depth to space).
    This skips the zeros a strided transposed convolution inserts between input pixels, and
    both its gradients are ordinary convolutions. At stride 1 it is a plain VALID convolution
    of the input padded by (k-1, k-1+op). tests/test_networks.py checks values and gradients
    against lax.conv_transpose.
    """

    features: int
    kernel: int
    stride: int = 1
    output_padding: int = 0
    dtype: Any = jnp.float32
    channels: int | None = None  # see Conv

    @nn.compact
    def __call__(self, x: jax.Array, weights_only: bool = False, phases: bool = False):
        """The layer of x; with `weights_only`, its (kernel, bias) for an input shaped like x;
        with `phases`, the output as its s x s phases, [..., size / s, size / s, (s, s, out)]
        (`space_to_depth` of the output; for sizes that are multiples of s)."""
        k, s, op = self.kernel, self.stride, self.output_padding
        n = x.shape[-2]
        kernel = self.param("kernel", conv_transpose_init, (k, k, x.shape[-1], self.features))
        bias = self.param("bias", ZEROS, (self.features,))
        if weights_only:
            return kernel, bias
        taps, size, per_phase = _subpixel_geometry(n, k, s, op)
        pad = (taps - 1, per_phase - n)
        # The barrier keeps XLA from folding the zero padding into the convolution: a padded
        # convolution's weight gradient is not matched to cuDNN's filter-gradient kernels and
        # ran 2-3x slower on an H100 (benchmarks/results/decoder_h100.json; DEAR update at batch
        # 512: 15.5 -> 10.3 ms per seed, benchmarks/results/update_h100_512.json).
        x = jax.lax.optimization_barrier(jnp.pad(x, ((0, 0),) * (x.ndim - 3) + (pad, pad, (0, 0))))
        w = _subpixel_kernel(kernel, s)
        if taps == 1:
            # k <= s: each output phase is a 1x1 convolution, i.e. one matrix product, which
            # a vmap over seeds batches into one GEMM (no per-seed cuDNN calls and slices).
            y = jnp.einsum("...c,cf->...f", x.astype(self.dtype), w[0, 0].astype(self.dtype))
        else:
            y = _conv2d(x, w, 1, self.dtype, self.channels or tensor_core_channels(self.dtype))
        if phases:
            _check_phases(size, s)
            return y + jnp.tile(bias, s * s).astype(self.dtype)
        y = _depth_to_space(y, s)[..., :size, :size, :]
        return y + bias.astype(self.dtype)


def _check_phases(size: int, s: int) -> None:
    if size % s:
        raise ValueError(f"an output of side {size} is not whole {s} x {s} phases")


def _subpixel_geometry(n: int, k: int, s: int, op: int) -> tuple[int, int, int]:
    """(kernel taps of one phase along an axis, output size, output pixels per phase along an
    axis) of a k x k transposed convolution with stride s and output padding op on n x n."""
    return (k - 1) // s + 1, (n - 1) * s + k + op, -(-((n - 1) * s + k + op) // s)


def _subpixel_kernel(kernel: jax.Array, s: int) -> jax.Array:
    """A transposed convolution's kernel [k, k, in, out] as the dense kernel of its s*s output
    phases, [taps, taps, in, (s, s, out)]: phase r, tap u reads input pixel m + u - (taps - 1)
    with kernel index s * (u - taps + 1) + k - 1 - r (zero where that is outside the kernel)."""
    k = kernel.shape[0]
    taps = (k - 1) // s + 1
    zero = jnp.zeros_like(kernel[0, 0])

    def tap(ry, uy, rx, ux):
        iy, ix = (s * (u - taps + 1) + k - 1 - r for r, u in ((ry, uy), (rx, ux)))
        return kernel[iy, ix] if 0 <= iy < k and 0 <= ix < k else zero

    rows = [
        [
            jnp.concatenate([tap(ry, uy, rx, ux) for ry in range(s) for rx in range(s)], -1)
            for ux in range(taps)
        ]
        for uy in range(taps)
    ]
    return jnp.stack([jnp.stack(row) for row in rows])


def space_to_depth(x: jax.Array, s: int) -> jax.Array:
    """[..., m * s, m * s, c] -> [..., m, m, (s, s, c)], the inverse of `_depth_to_space`:
    channel (ry, rx, c) of pixel (i, j) is channel c of pixel (s * i + ry, s * j + rx)."""
    *lead, h, _, c = x.shape
    x = x.reshape(*lead, h // s, s, h // s, s, c)
    x = jnp.moveaxis(x, -4, -3)  # [..., m, m, s, s, c]
    return x.reshape(*lead, h // s, h // s, s * s * c)


def _depth_to_space(y: jax.Array, s: int) -> jax.Array:
    """[..., m, m, (s, s, c)] -> [..., m * s, m * s, c]: channel (ry, rx, c) of pixel (i, j)
    becomes channel c of pixel (s * i + ry, s * j + rx)."""
    *lead, m, _, sc = y.shape
    y = y.reshape(*lead, m, m, s, s, sc // (s * s))
    y = jnp.moveaxis(y, -3, -4)  # [..., m, s, m, s, c]
    return y.reshape(*lead, m * s, m * s, sc // (s * s))


def _weights(modules, shape, dtype) -> list:
    """Each layer's (kernel, bias), layer i meeting the channels of layer i - 1's output."""
    weights = []
    for module in modules:
        weights.append(module(jax.ShapeDtypeStruct(shape, dtype), weights_only=True))
        shape = (*shape[:-1], weights[-1][0].shape[-1])
    return weights


def _pallas_trunk(obs: jax.Array, modules, dtype, crops) -> jax.Array | None:
    """The conv trunk (a stride-2 3x3 layer, then stride-1 3x3 layers, ReLU after each) of uint8
    pixels, read through `crops` if given, as one `wideconv.conv_stack`; None where that does
    not take the shapes.

    The stack's strided first layer reads the uint8 pixels themselves, so `preprocess` is
    folded into that layer: its kernel times PIXEL_SCALE, and PIXEL_ZERO * sum(kernel) added
    to its bias (every output of a VALID layer reads only pixels of the image).
    """
    *lead, h, w, c = obs.shape
    (k0, b0), *rest = _weights(modules, (h, w, c), dtype)
    bias = b0 + PIXEL_ZERO * jnp.sum(k0, axis=(0, 1, 2))
    layers = ((k0 * PIXEL_SCALE, bias), *rest)
    pixels, stride = obs.reshape(-1, h, w, c), modules[0].stride
    shift, offsets = (crops.pad, crops.offsets.reshape(-1, 2)) if crops else (0, None)
    if not wideconv.supported(pixels, layers, 0, stride, shift):
        return None
    y = wideconv.conv_stack(pixels, layers, 0, True, jnp.dtype(dtype), stride, shift, offsets)
    return y.reshape(*lead, *y.shape[1:])


def _pallas_decoder(x: jax.Array, modules, last, dtype, phases: bool, target=None, loss="bce"):
    """Stride-1 transposed 3x3 layers with ReLU (pad 2 each), then the last transposed layer
    (strided, no ReLU) as the dense 2x2 convolution of its output phases, as one
    `wideconv.conv_stack`, interleaved unless `phases`; with `target` (see `PoolDecoder`), the
    decoder's loss (`wideconv.LOSSES[loss]`), from `wideconv.conv_stack_loss`. None where that
    does not take the shapes."""
    *lead, n, _, c = x.shape
    *weights, (kernel, bias) = _weights([*modules, last], (n, n, c), dtype)
    n_last = n + 2 * len(modules)
    taps, size, per_phase = _subpixel_geometry(
        n_last, last.kernel, last.stride, last.output_padding
    )
    features = last.stride**2 * last.features
    channels = wideconv.channels_for(features)
    kernel = _pad_axis(_subpixel_kernel(kernel, last.stride), 3, channels)
    bias = _pad_axis(jnp.tile(bias, last.stride**2), 0, channels)
    layers = (*weights, (kernel, bias))
    pads = (2,) * len(modules) + (taps - 1,)
    flat = x.reshape(-1, n, n, c)
    if per_phase - n_last != taps - 1 or not wideconv.supported(flat, layers, pads):
        return None
    dtype = jnp.dtype(dtype)
    if phases or target is not None:
        _check_phases(size, last.stride)
    if target is not None:
        images, crops = _flat_target(target)
        shift, offsets = (crops.pad, crops.offsets) if crops else (0, None)
        total = wideconv.conv_stack_loss(
            flat, layers, images, pads, dtype, last.stride, shift, offsets, loss
        )
        return total / flat.shape[0]
    y = wideconv.conv_stack(flat, layers, pads, False, dtype)[..., :features]
    if not phases:
        y = _depth_to_space(y, last.stride)[:, :size, :size]
    return y.reshape(*lead, *y.shape[1:])


PIXEL_SCALE, PIXEL_ZERO = 1 / 255.0, -0.5  # preprocess: x * PIXEL_SCALE + PIXEL_ZERO


def preprocess(obs: jax.Array) -> jax.Array:
    """uint8 pixels [..., H, W, C] -> float32 in [-0.5, 0.5]."""
    return obs.astype(jnp.float32) * PIXEL_SCALE + PIXEL_ZERO


def avg_pool(x: jax.Array, k: int) -> jax.Array:
    """k x k average pooling with stride k and no padding ([..., H, W, C]; the rows and columns
    past the last whole window are dropped), as a reshape and a mean in float32. Its gradient is
    a broadcast; that of flax's `nn.avg_pool` (a reduce_window) is a dilated reduce_window,
    which took ~1 ms of a 5-seed bf16 DEAR update on an H100 (benchmarks/RESULTS.md)."""
    h, w = x.shape[-3] // k * k, x.shape[-2] // k * k
    x = x[..., :h, :w, :].reshape(*x.shape[:-3], h // k, k, w // k, k, x.shape[-1])
    return jnp.mean(x.astype(jnp.float32), axis=(-4, -2)).astype(x.dtype)


class ConvTrunk(nn.Module):
    """The four DrQ-v2 convolutions: 84 -> 41 -> 39 -> 37 -> 35, 32 channels, ReLU after each.

    Called with `crops` (augment.Crops), it encodes the cropped pixels: cropped first, or with
    Pallas stacks read through the crops by the first layer itself (no cropped copy).
    """

    dtype: Any = jnp.float32  # computation dtype (parameters stay float32)
    channels: int | None = None  # see Conv

    @nn.compact
    def __call__(self, obs: jax.Array, crops: augment.Crops | None = None) -> jax.Array:
        layers = [Conv(32, 2 if i == 0 else 1, self.dtype, self.channels) for i in range(4)]
        if _CONV.get().stack == "pallas":
            y = _pallas_trunk(obs, layers, self.dtype, crops)
            if y is not None:
                return y
        if crops is not None:
            obs = crops.apply(obs)
        if (self.channels or tensor_core_channels(self.dtype)) > 1:
            # XLA fuses the random shift's gather with the conversion to float and the channel
            # padding into one slow kernel; kept apart, the bf16 trunk took 1.78 instead of
            # 2.36 ms (H100, benchmarks/results/encoder_input_h100.json: shift_apart vs pad).
            obs = jax.lax.optimization_barrier(obs)
        x = preprocess(obs).astype(self.dtype)
        for layer in layers:
            x = nn.relu(layer(x))
        return x


class PoolEncoder(nn.Module):
    """DEAR's encoder: conv trunk, 4x4 average pool (35 -> 8), Linear(2048 -> latent_dim)."""

    latent_dim: int = 4096
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, obs: jax.Array, crops: augment.Crops | None = None) -> jax.Array:
        """uint8 [..., 84, 84, 9] (cropped by `crops` if given) -> f32 [..., latent]."""
        x = ConvTrunk(self.dtype)(obs, crops)
        x = avg_pool(x, 4)
        x = x.reshape(*x.shape[:-3], -1)
        return _dense(self.latent_dim, dtype=self.dtype)(x).astype(jnp.float32)


class PlainEncoder(nn.Module):
    """DrQ-v2's encoder: conv trunk flattened (35*35*32 = 39200), no projection."""

    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, obs: jax.Array, crops: augment.Crops | None = None) -> jax.Array:
        x = ConvTrunk(self.dtype)(obs, crops)
        return x.reshape(*x.shape[:-3], -1).astype(jnp.float32)


def encoder_module(kind: str, latent_dim: int, dtype: Any = jnp.float32) -> nn.Module:
    if kind == "pool":
        return PoolEncoder(latent_dim, dtype)
    if kind == "plain":
        return PlainEncoder(dtype)
    raise ValueError(f"unknown encoder {kind!r}; valid: 'pool', 'plain'")


class Trunk(nn.Module):
    """Linear(latent -> feature_dim), LayerNorm, Tanh: the actor's and the critic's input layer."""

    feature_dim: int = 50
    products: Any = jnp.float32  # the Linear's product operands (see `mixed_dot_general`)

    @nn.compact
    def __call__(self, z: jax.Array) -> jax.Array:
        # epsilon 1e-5: PyTorch's LayerNorm default, which DrQ-v2 uses (Flax's is 1e-6).
        x = _dense(self.feature_dim, products=self.products)(z)
        return jnp.tanh(nn.LayerNorm(epsilon=1e-5)(x))


class MLP(nn.Module):
    hidden: Sequence[int]
    out: int
    products: Any = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for h in self.hidden:
            x = nn.relu(_dense(h, products=self.products)(x))
        return _dense(self.out, products=self.products)(x)


class Actor(nn.Module):
    """Deterministic mean of the DrQ-v2 policy: tanh(MLP(trunk(z))) in [-1, 1]^|A|.

    `products`: the dtype of its matrix products' operands (float32 results either way)."""

    action_dim: int
    feature_dim: int = 50
    hidden_dim: int = 1024
    products: Any = jnp.float32

    @nn.compact
    def __call__(self, z: jax.Array) -> jax.Array:
        h = Trunk(self.feature_dim, self.products)(z)
        mlp = MLP((self.hidden_dim, self.hidden_dim), self.action_dim, self.products)
        return jnp.tanh(mlp(h))


class Critic(nn.Module):
    """Twin Q heads on a shared trunk: (z, a) -> (Q1, Q2), each of shape [...]. `products`: as
    the actor's."""

    feature_dim: int = 50
    hidden_dim: int = 1024
    products: Any = jnp.float32

    @nn.compact
    def __call__(self, z: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        h = jnp.concatenate([Trunk(self.feature_dim, self.products)(z), action], axis=-1)
        hidden = (self.hidden_dim, self.hidden_dim)
        q1 = MLP(hidden, 1, self.products, name="q1")(h)[..., 0]
        q2 = MLP(hidden, 1, self.products, name="q2")(h)[..., 0]
        return q1, q2


# PoolDecoder's losses with a target (as wideconv.LOSSES, summed over pixels, mean over images).
DECODER_LOSSES = {"bce": losses.mask_loss, "clipped_squares": losses.reconstruction_loss}
DECODER_STRIDE = 2  # PoolDecoder's last layer
DECODER_SIDE = 84  # PoolDecoder's output side


def decoder_phases(image: jax.Array) -> jax.Array:
    """An image [..., 84, 84, C] as `PoolDecoder(phases=True)` lays out its output."""
    return space_to_depth(image, DECODER_STRIDE)


class PoolDecoder(nn.Module):
    """Mirror of the pool encoder: [..., in_dim] -> [..., 84, 84, out_channels] (no output activation).

    Linear -> 8x8x16 -> ConvT 4x4/4 (+3) -> 35 -> 37 -> 39 -> 41 -> ConvT 3x3/2 (+1) -> 84.
    The mask decoder (3 channels, `loss` "bce") returns logits; the sigmoid lives in the loss.
    The SEAR reconstruction decoder (9 channels, `loss` "clipped_squares") returns pixels in
    the [-0.5, 0.5] scale.

    With `phases`, the output is returned as the last layer computes it, its 2x2 phases
    [..., 42, 42, 4 * out_channels]: `decoder_phases` of the image. A loss summed over pixels
    is the same on either; on phases, neither the output nor its gradient is interleaved.

    With `target` = (images, crops): [..., 84, 84, out_channels] (the leading axes of z) and
    the random shift's `augment.Crops` (or None: the images as they are), the decoder's loss
    instead (`phases` does not matter), averaged over all the leading axes: for "bce",
    `losses.mask_loss` of the logits against {0, 1} masks; for "clipped_squares",
    `losses.reconstruction_loss` of the output against uint8 frames; each against the cropped
    images. With Pallas stacks, the last layer's kernel computes the loss and its gradient as
    it computes the output (`wideconv.conv_stack_loss`), and no other pass reads or writes it;
    it takes the loss of the float32 output, where XLA's path takes that of the output in the
    decoder's dtype (bf16 mask loss: both within 1e-4 of the float32 loss, relative;
    benchmarks/results/mask_loss_h100.json, commit b60ebbf).
    """

    out_channels: int
    dtype: Any = jnp.float32
    loss: str = "bce"  # the loss taken with a target: a key of wideconv.LOSSES

    @nn.compact
    def __call__(self, z: jax.Array, phases: bool = False, target=None) -> jax.Array:
        dt = self.dtype
        if target is not None:
            want = (*z.shape[:-1], DECODER_SIDE, DECODER_SIDE, self.out_channels)
            if target[0].shape != want:
                raise ValueError(f"the decoder's target images are {target[0].shape}, need {want}")
        x = nn.relu(_dense(16 * 8 * 8, dtype=dt)(z))
        x = x.reshape(*x.shape[:-1], 8, 8, 16)
        x = nn.relu(ConvTranspose(16, 4, stride=4, output_padding=3, dtype=dt)(x))
        layers = [ConvTranspose(features, 3, dtype=dt) for features in (32, 32, 32)]
        last = ConvTranspose(
            self.out_channels, 3, stride=DECODER_STRIDE, output_padding=1, dtype=dt
        )
        if _CONV.get().stack == "pallas":
            y = _pallas_decoder(x, layers, last, dt, phases, target, self.loss)
            if y is not None:
                return y.astype(jnp.float32)
        for layer in layers:
            x = nn.relu(layer(x))
        if target is None:
            return last(x, phases=phases).astype(jnp.float32)
        out = last(x, phases=True).astype(jnp.float32)
        images, crops = _flat_target(target)
        images = decoder_phases(crops.apply(images) if crops else images)
        loss = DECODER_LOSSES[self.loss]
        return loss(out.reshape(-1, *out.shape[-3:]), images)


def _flat_target(target):
    """A decoder's (masks, crops or None) with their leading axes as one."""
    mask, crops = target
    if crops is not None:
        crops = crops._replace(offsets=crops.offsets.reshape(-1, 2))
    return mask.reshape(-1, *mask.shape[-3:]), crops


class TEDClassifier(nn.Module):
    """TED's temporal classifier on a pair of latents (z1, z2) -> logit.

    logit = sum_F(|W0*z1 + W1*z2 + b| - (Wb*z1 + bb)^2) + c, all products elementwise, with
    orthogonally initialised [1, F] rows; form "strict" draws each row apart and starts c at 0,
    "reference_code" draws W0 and W1 as one orthogonal [2, F] matrix and c as an orthogonal
    1 x 1 (+-1), as TED's code (`losses.TED_FORMS`).
    """

    form: str = "strict"

    @nn.compact
    def __call__(self, z1: jax.Array, z2: jax.Array) -> jax.Array:
        f = z1.shape[-1]
        row = lambda name: self.param(name, LINEAR_INIT, (1, f))[0]  # noqa: E731
        reference = self.form == "reference_code"
        w0, w1 = self.param("w01", LINEAR_INIT, (2, f)) if reference else (row("w0"), row("w1"))
        b, wb, bb = (row(n) for n in ("b", "wb", "bb"))
        c = self.param("c", LINEAR_INIT, (1, 1))[0, 0] if reference else self.param("c", ZEROS, ())
        return jnp.sum(jnp.abs(w0 * z1 + w1 * z2 + b) - (wb * z1 + bb) ** 2, axis=-1) + c
