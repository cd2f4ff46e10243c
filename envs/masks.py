"""Agent masks from pixel labels, and the two degraded variants of the ablations (docs/method.md, Masks).

All functions are pure jnp on [..., H, W] arrays (any leading dims), so they run on the
accelerator inside the env step and vmap freely.

- `agent_mask`: 1 where the label is AGENT.
- `noisy_mask`: each agent pixel dropped (1 -> 0) independently with probability p.
- `approximate_mask`: resize 84 -> 28 bilinear, back to 84 bilinear, Gaussian blur sigma 0.5,
  keep > 0.9. Bilinear here is the plain two-tap kind of OpenCV's INTER_LINEAR and PyTorch's
  `interpolate(align_corners=False)` (no anti-aliasing filter), so 84 -> 28 samples every third
  pixel (rows and columns 1, 4, ..., 82). The blur is a 5-tap kernel (OpenCV's size for
  sigma 0.5) with mirrored borders (OpenCV's BORDER_REFLECT_101); tests check the result equals
  OpenCV's.

What "approximate masks are subsets of the true mask" means exactly: the result is the mask
eroded as seen on the 28x28 sampling grid (isolated pixels and parts 1-2 pixels wide vanish,
borders move in), but it is NOT a strict subset. Guarantee: every approximate-mask pixel is
within one pixel (8-neighbourhood) of a true-mask pixel. Proof: after the blur (centre weight
0.787^2 = 0.619, the rest 0.381) a pixel exceeds 0.9 only if its upsampled value exceeds
(0.9 - 0.381) / 0.619 = 0.84; its nearest grid sample is at most one pixel away in each axis and
carries a bilinear weight >= 4/9, so if that sample were 0 the value would be <= 5/9. Pixels
outside the true mask do appear where the mask bends within a 3x3 grid cell (a concave corner, a
gap between two limbs narrower than the grid): on rendered walker masks about 0.6% of the
approximate mask's pixels, a few % on the thin cup (tests/test_masks.py measures it and checks
the bound). The image border adds a second case: pixel 0 copies grid sample 1 (and pixel 83
sample 82), so a mask reaching row or column 1 spills onto row or column 0. Axis-aligned
rectangles that keep two pixels from the border give a strict subset.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from envs.labels import LABEL_AGENT

APPROX_SMALL = 28  # the intermediate resolution of the approximate mask
APPROX_SIGMA = 0.5
APPROX_THRESHOLD = 0.9


def agent_mask(labels: jax.Array) -> jax.Array:
    """labels uint8 [..., H, W] -> uint8 [..., H, W] in {0, 1}."""
    return (labels == LABEL_AGENT).astype(jnp.uint8)


def noisy_mask(mask: jax.Array, key: jax.Array, p: float) -> jax.Array:
    """Drops each agent pixel with probability p. mask uint8 [..., H, W] -> same shape/dtype."""
    keep = jax.random.bernoulli(key, 1.0 - p, mask.shape)
    return mask * keep.astype(mask.dtype)


def gaussian_taps(sigma: float) -> np.ndarray:
    """Normalised taps of a sampled Gaussian, OpenCV's length for float images (8 sigma + 1)."""
    size = int(round(sigma * 8 + 1)) | 1
    x = np.arange(size) - size // 2
    taps = np.exp(-(x**2) / (2 * sigma**2))
    return (taps / taps.sum()).astype(np.float32)


def _blur_axis(x: jax.Array, taps: np.ndarray, axis: int) -> jax.Array:
    half = len(taps) // 2
    pad = [(0, 0)] * x.ndim
    pad[axis] = (half, half)
    xp = jnp.pad(x, pad, mode="reflect")  # numpy's "reflect" = OpenCV's BORDER_REFLECT_101
    n = x.shape[axis]
    return sum(float(t) * jax.lax.slice_in_dim(xp, i, i + n, axis=axis) for i, t in enumerate(taps))


def gaussian_blur(x: jax.Array, sigma: float) -> jax.Array:
    """Separable Gaussian blur of the last two axes. x float [..., H, W]."""
    taps = gaussian_taps(sigma)
    return _blur_axis(_blur_axis(x, taps, x.ndim - 2), taps, x.ndim - 1)


def approximate_mask_values(mask: jax.Array) -> jax.Array:
    """The blurred float values the approximate mask thresholds. mask [..., H, W] -> f32."""
    h, w = mask.shape[-2:]
    lead = mask.shape[:-2]
    x = mask.astype(jnp.float32)
    small = jax.image.resize(x, (*lead, APPROX_SMALL, APPROX_SMALL), "bilinear", antialias=False)
    big = jax.image.resize(small, (*lead, h, w), "bilinear", antialias=False)
    return gaussian_blur(big, APPROX_SIGMA)


def approximate_mask(mask: jax.Array) -> jax.Array:
    """mask uint8 [..., H, W] in {0,1} -> uint8 [..., H, W]: the resize/blur/threshold recipe."""
    return (approximate_mask_values(mask) > APPROX_THRESHOLD).astype(jnp.uint8)


def make_mask(labels: jax.Array, key: jax.Array, kind: str, drop_prob: float) -> jax.Array:
    """The training target variant: kind in ("true", "noisy", "approximate")."""
    mask = agent_mask(labels)
    if kind == "true":
        return mask
    if kind == "noisy":
        return noisy_mask(mask, key, drop_prob)
    if kind == "approximate":
        return approximate_mask(mask)
    raise ValueError(f"unknown mask kind {kind!r}; valid: 'true', 'noisy', 'approximate'")
