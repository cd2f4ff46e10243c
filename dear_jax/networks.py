"""Flax modules of DrQ-v2 and the auxiliary heads of DEAR, SEAR and TED (REFERENCE.md sections 1-3).

Every module works on one unbatched-or-batched array with channels last; seeds are added by
`jax.vmap` at the call site, never here. Initialisation follows DrQ-v2: orthogonal weights (gain 1
for linear layers, sqrt(2) for convolutions and transposed convolutions), zero biases.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

LINEAR_INIT = nn.initializers.orthogonal(1.0)
CONV_INIT = nn.initializers.orthogonal(math.sqrt(2.0))
ZEROS = nn.initializers.zeros


def _dense(features: int, name: str | None = None, dtype=jnp.float32) -> nn.Dense:
    return nn.Dense(features, kernel_init=LINEAR_INIT, bias_init=ZEROS, name=name, dtype=dtype)


def _conv(features: int, stride: int, dtype=jnp.float32) -> nn.Conv:
    return nn.Conv(
        features,
        (3, 3),
        strides=(stride, stride),
        padding="VALID",
        kernel_init=CONV_INIT,
        bias_init=ZEROS,
        dtype=dtype,
    )


class PaddedConv(nn.Module):
    """Explicit zero padding, then a VALID convolution (see `_conv_transpose` for why)."""

    features: int
    kernel: int
    pad: tuple[int, int]
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        spatial = (self.pad, self.pad)
        x = jnp.pad(x, ((0, 0),) * (x.ndim - 3) + spatial + ((0, 0),))
        return nn.Conv(
            self.features,
            (self.kernel, self.kernel),
            padding="VALID",
            kernel_init=CONV_INIT,
            bias_init=ZEROS,
            dtype=self.dtype,
        )(x)


def _conv_transpose(
    features: int, kernel: int, stride: int = 1, output_padding: int = 0, dtype=jnp.float32
) -> nn.Module:
    """PyTorch's ConvTranspose2d(kernel, stride, output_padding): (in-1)*stride + kernel + op.

    lax.conv_transpose with explicit (k-1, k-1+op) padding gives that size, and the reference
    decoder's shapes rely on it. At stride 1 the same function is a VALID convolution, with the
    same (unflipped) kernel, of the input zero-padded by (k-1, k-1+op). Written that way the
    weight gradient is an ordinary convolution, which XLA:CPU runs far faster: one DEAR update
    at batch 256 on 2 CPU cores took 45.5 s before and 6.6 s after (benchmarks/update.py,
    benchmarks/results/update_cpu.json). tests/test_networks.py checks the two forms agree.
    """
    pad = (kernel - 1, kernel - 1 + output_padding)
    if stride == 1:
        return PaddedConv(features, kernel, pad, dtype)
    return nn.ConvTranspose(
        features,
        (kernel, kernel),
        strides=(stride, stride),
        padding=(pad, pad),
        kernel_init=CONV_INIT,
        bias_init=ZEROS,
        dtype=dtype,
    )


def preprocess(obs: jax.Array) -> jax.Array:
    """uint8 pixels [..., H, W, C] -> float32 in [-0.5, 0.5]."""
    return obs.astype(jnp.float32) / 255.0 - 0.5


class ConvTrunk(nn.Module):
    """The four DrQ-v2 convolutions: 84 -> 41 -> 39 -> 37 -> 35, 32 channels, ReLU after each."""

    dtype: Any = jnp.float32  # computation dtype (parameters stay float32)

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        x = preprocess(obs).astype(self.dtype)
        x = nn.relu(_conv(32, 2, self.dtype)(x))
        for _ in range(3):
            x = nn.relu(_conv(32, 1, self.dtype)(x))
        return x


class PoolEncoder(nn.Module):
    """DEAR's encoder: conv trunk, 4x4 average pool (35 -> 8), Linear(2048 -> latent_dim)."""

    latent_dim: int = 4096
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:  # uint8 [..., 84, 84, 9] -> f32 [..., latent]
        x = ConvTrunk(self.dtype)(obs)
        x = nn.avg_pool(x, (4, 4), strides=(4, 4), padding="VALID")
        x = x.reshape(*x.shape[:-3], -1)
        return _dense(self.latent_dim, dtype=self.dtype)(x).astype(jnp.float32)


class PlainEncoder(nn.Module):
    """DrQ-v2's encoder: conv trunk flattened (35*35*32 = 39200), no projection."""

    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        x = ConvTrunk(self.dtype)(obs)
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

    @nn.compact
    def __call__(self, z: jax.Array) -> jax.Array:
        return jnp.tanh(nn.LayerNorm()(_dense(self.feature_dim)(z)))


class MLP(nn.Module):
    hidden: Sequence[int]
    out: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for h in self.hidden:
            x = nn.relu(_dense(h)(x))
        return _dense(self.out)(x)


class Actor(nn.Module):
    """Deterministic mean of the DrQ-v2 policy: tanh(MLP(trunk(z))) in [-1, 1]^|A|."""

    action_dim: int
    feature_dim: int = 50
    hidden_dim: int = 1024

    @nn.compact
    def __call__(self, z: jax.Array) -> jax.Array:
        h = Trunk(self.feature_dim)(z)
        return jnp.tanh(MLP((self.hidden_dim, self.hidden_dim), self.action_dim)(h))


class Critic(nn.Module):
    """Twin Q heads on a shared trunk: (z, a) -> (Q1, Q2), each of shape [...]."""

    feature_dim: int = 50
    hidden_dim: int = 1024

    @nn.compact
    def __call__(self, z: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        h = jnp.concatenate([Trunk(self.feature_dim)(z), action], axis=-1)
        hidden = (self.hidden_dim, self.hidden_dim)
        q1 = MLP(hidden, 1, name="q1")(h)[..., 0]
        q2 = MLP(hidden, 1, name="q2")(h)[..., 0]
        return q1, q2


class PoolDecoder(nn.Module):
    """Mirror of the pool encoder: [..., in_dim] -> [..., 84, 84, out_channels] (no output activation).

    Linear -> 8x8x16 -> ConvT 4x4/4 (+3) -> 35 -> 37 -> 39 -> 41 -> ConvT 3x3/2 (+1) -> 84.
    The mask decoder (3 channels) returns logits; the sigmoid lives in the loss. The SEAR
    reconstruction decoder (9 channels) returns pixels in the [-0.5, 0.5] scale.
    """

    out_channels: int
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, z: jax.Array) -> jax.Array:
        dt = self.dtype
        x = nn.relu(_dense(16 * 8 * 8, dtype=dt)(z))
        x = x.reshape(*x.shape[:-1], 8, 8, 16)
        x = nn.relu(_conv_transpose(16, 4, stride=4, output_padding=3, dtype=dt)(x))
        for features in (32, 32, 32):
            x = nn.relu(_conv_transpose(features, 3, dtype=dt)(x))
        out = _conv_transpose(self.out_channels, 3, stride=2, output_padding=1, dtype=dt)(x)
        return out.astype(jnp.float32)


class TEDClassifier(nn.Module):
    """TED's temporal classifier on a pair of latents (z1, z2) -> logit.

    logit = sum_F(|W0*z1 + W1*z2 + b| - (Wb*z1 + bb)^2) + c, all products elementwise, with
    orthogonally initialised [1, F] rows.
    """

    @nn.compact
    def __call__(self, z1: jax.Array, z2: jax.Array) -> jax.Array:
        f = z1.shape[-1]
        row = lambda name: self.param(name, LINEAR_INIT, (1, f))[0]  # noqa: E731
        w0, w1, b, wb, bb = (row(n) for n in ("w0", "w1", "b", "wb", "bb"))
        c = self.param("c", ZEROS, ())
        return jnp.sum(jnp.abs(w0 * z1 + w1 * z2 + b) - (wb * z1 + bb) ** 2, axis=-1) + c
