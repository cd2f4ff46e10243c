"""Random shift = integer crop of the edge-padded image; obs and mask move together."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dear_jax import augment


def test_shift_equals_crop_of_edge_padded_image():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (84, 84, 9), dtype=np.uint8)
    padded = np.pad(image, ((4, 4), (4, 4), (0, 0)), mode="edge")
    for dy, dx in [(0, 0), (8, 8), (3, 7), (8, 0)]:
        out = augment.shift(jnp.asarray(image), jnp.array([dy, dx]))
        np.testing.assert_array_equal(out, padded[dy : dy + 84, dx : dx + 84])
    centre = augment.shift(jnp.asarray(image), jnp.array([4, 4]))
    np.testing.assert_array_equal(centre, image)


def test_offsets_cover_zero_to_eight():
    keys = jax.random.split(jax.random.key(0), 2000)
    offsets = np.asarray(jax.vmap(augment.sample_offset)(keys))
    assert offsets.min() == 0 and offsets.max() == 8
    assert set(np.unique(offsets)) == set(range(9))


def test_pair_shift_moves_obs_and_mask_together():
    rng = np.random.default_rng(1)
    obs = jnp.asarray(rng.integers(0, 256, (16, 84, 84, 9), dtype=np.uint8))
    # The mask is a copy of obs channels, so a shared shift keeps them equal after shifting.
    mask = obs[..., :3]
    crops = augment.Crops.sample(jax.random.key(3), 16)
    s_obs, s_mask = jax.jit(lambda o, m: (crops.apply(o), crops.apply(m)))(obs, mask)
    np.testing.assert_array_equal(s_obs[..., :3], s_mask)
    # And the samples of the batch got different shifts.
    shifted = [not np.array_equal(s_obs[i], obs[i]) for i in range(16)]
    assert sum(shifted) >= 12


def test_batch_shift_is_independent_per_sample():
    obs = jnp.tile(jnp.arange(84, dtype=jnp.uint8)[None, None, :, None], (32, 84, 1, 3))
    out = np.asarray(augment.random_shift_batch(obs, jax.random.key(4)))
    # Output column 8 shows image column 4 + dx, which tells each sample's horizontal offset.
    dxs = {int(out[i, 0, 8, 0]) - 4 for i in range(32)}
    assert dxs <= set(range(9)) and len(dxs) > 3


@pytest.mark.parametrize("impl", ["gather", "one_hot"])
def test_every_shift_impl_gives_pad_slices_pixels(impl):
    """The rewrites select the same pixels (edge rows and columns repeated) as the edge-pad and
    crop, for uint8 frames and 0/1 masks, at the extreme offsets and inside, jitted and vmapped."""
    rng = np.random.default_rng(5)
    image = jnp.asarray(rng.integers(0, 256, (84, 84, 9), dtype=np.uint8))
    mask = jnp.asarray(rng.integers(0, 2, (84, 84, 3), dtype=np.uint8))
    for x in (image, mask):
        for offset in ((0, 0), (8, 8), (0, 8), (3, 6)):
            want = augment.shift(x, jnp.array(offset))
            got = jax.jit(augment.shift, static_argnums=(2, 3))(x, jnp.array(offset), 4, impl)
            assert got.dtype == x.dtype
            np.testing.assert_array_equal(got, want)
    obs = jnp.asarray(rng.integers(0, 256, (8, 84, 84, 9), dtype=np.uint8))
    key = jax.random.key(6)
    want = augment.random_shift_batch(obs, key)
    got = augment.Crops.sample(key, 8, impl=impl).apply(obs)
    np.testing.assert_array_equal(got, want)


def test_unknown_shift_impl_is_refused_by_name():
    image = jnp.zeros((84, 84, 3), jnp.uint8)
    with pytest.raises(ValueError, match="unknown shift_impl 'roll'.*pad_slice"):
        augment.shift(image, jnp.array([0, 0]), impl="roll")
    with pytest.raises(ValueError, match="uint8 images only"):
        augment.shift(image.astype(jnp.float32), jnp.array([0, 0]), impl="one_hot")
