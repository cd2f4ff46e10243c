"""DrQ-v2's random-shift augmentation: edge-pad by `pad` pixels, crop back at an integer offset.

`shift` crops one image; `Crops` holds a batch's offsets, drawn once, so an observation and its
mask share one shift and the mask target stays aligned with the pixels the encoder sees.

The crop can be computed three ways that give the same pixels (`SHIFT_IMPLS`, the update's
`agent.shift_impl`); they differ in speed only (measured at commit 30f40af; benchmarks/results/shift_h100.json):
- "pad_slice": edge-pad, then a dynamic slice (vmapped: one gather of whole crops);
- "gather": no padded copy; take the rows clip(y + dy - pad), then the columns;
- "one_hot": the same row and column selection as two matrix products with one-hot matrices, in
  bf16 with float32 accumulation: exact for uint8 pixels, as every output is one pixel times 1
  and bf16 holds the integers 0..256.
The functions here default to "pad_slice", the definition; the trainer uses `agent.shift_impl`
(default "gather", the fastest on an H100).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

DEFAULT_PAD = 4
SHIFT_IMPLS = ("pad_slice", "gather", "one_hot")


def _source(n: int, offset: jax.Array, pad: int) -> jax.Array:
    """Source index of each of n output positions: the edge-padded crop at `offset`."""
    return jnp.clip(jnp.arange(n) + offset - pad, 0, n - 1)


def shift(
    image: jax.Array, offset: jax.Array, pad: int = DEFAULT_PAD, impl: str = "pad_slice"
) -> jax.Array:
    """Crop [H, W, C] out of the edge-padded image at integer `offset` = (dy, dx) in [0, 2*pad]."""
    h, w, c = image.shape
    if impl == "pad_slice":
        padded = jnp.pad(image, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
        return jax.lax.dynamic_slice(padded, (offset[0], offset[1], 0), (h, w, c))
    rows, cols = _source(h, offset[0], pad), _source(w, offset[1], pad)
    if impl == "gather":
        # The indices are clipped already: mode "clip" spares the gathers the out-of-bounds
        # masks of the default mode ("fill"), which XLA otherwise evaluates for every pixel
        # read, in each fusion the crops are read into (the mask loss and its gradient).
        take = lambda x, idx, axis: jnp.take(x, idx, axis=axis, mode="clip")  # noqa: E731
        return take(take(image, rows, 0), cols, 1)
    if impl == "one_hot":
        if image.dtype != jnp.uint8:
            raise ValueError(
                f"shift_impl 'one_hot' is exact for uint8 images only, got {image.dtype}"
            )
        bf16, f32 = jnp.bfloat16, jnp.float32
        x = jnp.einsum(
            "ih,hwc->iwc",
            jax.nn.one_hot(rows, h, dtype=bf16),
            image.astype(bf16),
            preferred_element_type=f32,
        ).astype(bf16)
        x = jnp.einsum(
            "jw,iwc->ijc", jax.nn.one_hot(cols, w, dtype=bf16), x, preferred_element_type=f32
        )
        return x.astype(image.dtype)
    raise ValueError(f"unknown shift_impl {impl!r}; valid: {', '.join(SHIFT_IMPLS)}")


def sample_offset(key: jax.Array, pad: int = DEFAULT_PAD) -> jax.Array:
    """One (dy, dx), each uniform in {0, ..., 2*pad}."""
    return jax.random.randint(key, (2,), 0, 2 * pad + 1)


class Crops(NamedTuple):
    """A batch's random-shift crops, not yet applied: each image's offset [B, 2], the pad and
    the impl. The encoder takes them with the uncropped pixels (it may read the crops
    directly: `networks.ConvTrunk`); `apply` crops any batch aligned with them (masks)."""

    offsets: jax.Array
    pad: int = DEFAULT_PAD
    impl: str = "pad_slice"

    @classmethod
    def sample(cls, key: jax.Array, n: int, pad: int = DEFAULT_PAD, impl: str = "pad_slice"):
        """Independent offsets for n images (those of `random_shift_batch` with this key)."""
        keys = jax.random.split(key, n)
        return cls(jax.vmap(sample_offset, in_axes=(0, None))(keys, pad), pad, impl)

    def apply(self, images: jax.Array) -> jax.Array:
        """Each image of a batch [B, H, W, C] cropped at its offset."""
        shift_each = jax.vmap(shift, in_axes=(0, 0, None, None))
        return shift_each(images, self.offsets, self.pad, self.impl)


def random_shift_batch(
    images: jax.Array, key: jax.Array, pad: int = DEFAULT_PAD, impl: str = "pad_slice"
) -> jax.Array:
    """Independent shifts for a batch [B, H, W, C]."""
    return Crops.sample(key, images.shape[0], pad, impl).apply(images)
