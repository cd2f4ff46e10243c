"""DrQ-v2's random-shift augmentation: edge-pad by `pad` pixels, crop back at an integer offset.

Written for one image and vmapped by the caller. An observation and its mask share one shift, so
the mask target stays aligned with the pixels the encoder sees.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

DEFAULT_PAD = 4


def shift(image: jax.Array, offset: jax.Array, pad: int = DEFAULT_PAD) -> jax.Array:
    """Crop [H, W, C] out of the edge-padded image at integer `offset` = (dy, dx) in [0, 2*pad]."""
    h, w, c = image.shape
    padded = jnp.pad(image, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
    return jax.lax.dynamic_slice(padded, (offset[0], offset[1], 0), (h, w, c))


def sample_offset(key: jax.Array, pad: int = DEFAULT_PAD) -> jax.Array:
    """One (dy, dx), each uniform in {0, ..., 2*pad}."""
    return jax.random.randint(key, (2,), 0, 2 * pad + 1)


def random_shift(image: jax.Array, key: jax.Array, pad: int = DEFAULT_PAD) -> jax.Array:
    """Randomly shifted copy of one image [H, W, C]."""
    return shift(image, sample_offset(key, pad), pad)


def random_shift_pair(
    image: jax.Array, mask: jax.Array, key: jax.Array, pad: int = DEFAULT_PAD
) -> tuple[jax.Array, jax.Array]:
    """Shift an image [H, W, C] and its mask [H, W, K] by the same random offset."""
    offset = sample_offset(key, pad)
    return shift(image, offset, pad), shift(mask, offset, pad)


def random_shift_batch(images: jax.Array, key: jax.Array, pad: int = DEFAULT_PAD) -> jax.Array:
    """Independent shifts for a batch [B, H, W, C]."""
    keys = jax.random.split(key, images.shape[0])
    return jax.vmap(random_shift, in_axes=(0, 0, None))(images, keys, pad)


def random_shift_pair_batch(
    images: jax.Array, masks: jax.Array, key: jax.Array, pad: int = DEFAULT_PAD
) -> tuple[jax.Array, jax.Array]:
    """Independent shifts per sample for a batch, each shared by the sample's image and mask."""
    keys = jax.random.split(key, images.shape[0])
    return jax.vmap(random_shift_pair, in_axes=(0, 0, 0, None))(images, masks, keys, pad)
