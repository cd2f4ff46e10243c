"""benchmarks/conv_mgpu.py: the grid layout its Mosaic GPU kernel computes on (the kernel itself
needs a Hopper GPU; its outputs are checked against XLA's there, by the script)."""

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import conv_mgpu


def test_grid_places_pixels_at_their_rows_and_pads_zeros():
    x = jnp.asarray(np.random.default_rng(0).normal(size=(2, 5, 5, 3)), jnp.float32)
    width, block = 8, 16
    g = np.asarray(conv_mgpu.to_grid(x, width, block))
    pixels = 2 * 5 * width
    assert g.shape == (-(-pixels // block) * block + conv_mgpu.halo(width), 3)
    assert np.array_equal(g[(1 * 5 + 3) * width + 4], np.asarray(x[1, 3, 4]))
    assert (
        not g.reshape(-1, 3)[:pixels].reshape(2, 5, width, 3)[:, :, 5:].any()
    )  # the columns past H
    assert not g[pixels:].any()
    back = conv_mgpu.from_grid(jnp.asarray(g), 2, 5, width, valid=5)
    assert np.array_equal(np.asarray(back), np.asarray(x))


def test_taps_as_row_shifts_of_the_grid_are_the_valid_convolution():
    """What the kernel computes, out[q] = relu(sum_ij x[q + i * width + j] @ w[i, j]) over the
    grid's rows, read back at the valid pixels, is XLA's VALID convolution with ReLU."""
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=(2, 7, 7, 4)), jnp.float32)
    w = jnp.asarray(rng.normal(size=(3, 3, 4, 5)), jnp.float32)
    width, block = 8, 8
    g = conv_mgpu.to_grid(x, width, block)
    rows = g.shape[0] - conv_mgpu.halo(width)
    out = sum(g[i * width + j : i * width + j + rows] @ w[i, j] for i in range(3) for j in range(3))
    got = conv_mgpu.from_grid(jax.nn.relu(out), 2, 7, width, valid=5)
    want = jax.nn.relu(
        jax.lax.conv_general_dilated(
            x, w, (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"), precision="highest"
        )
    )
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-5)
