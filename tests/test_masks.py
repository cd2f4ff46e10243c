"""Agent masks: the true mask, noisy (drop p) and approximate (resize/blur/threshold) variants."""

import copy
import importlib.util
import os
import pathlib

os.environ.setdefault("MUJOCO_GL", "egl")

import cv2
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from envs import masks as M
from envs import render as R
from envs.labels import LABEL_AGENT, LABEL_BACKGROUND, LABEL_FLOOR, LABEL_OTHER

SUITE = pathlib.Path(importlib.util.find_spec("dm_control").origin).parent / "suite"


def rendered_masks(xml, agent_bodies, n=60, seed=0):
    model = mujoco.MjModel.from_xml_path(str(SUITE / xml))
    roots = {model.body(b).id for b in agent_bodies}
    agent = []  # geoms of the agent bodies and their subtrees (walker's limbs)
    for g in range(model.ngeom):
        b = model.geom_bodyid[g]
        while b and b not in roots:
            b = model.body_parentid[b]
        if b:
            agent.append(g)
    rng = np.random.default_rng(seed)
    qpos = np.tile(model.qpos0, (n, 1)) + rng.normal(0, 0.4, (n, model.nq))
    tr = R.TileRenderer(
        copy.deepcopy(model),
        camera=0,
        agent_geom_ids=agent,
        floor_geom_ids=[0],
        settings=R.RenderSettings(tiles_per_sheet=1),
    )
    rgb = np.zeros((n, 84, 84, 3), np.uint8)
    labels = np.zeros((n, 84, 84), np.uint8)
    tr.render(qpos, rgb, labels)
    tr.close()
    return np.asarray(M.agent_mask(jnp.asarray(labels)))


@pytest.fixture(scope="module")
def masks():
    return {
        "walker": rendered_masks("walker.xml", ("torso",)),
        "cup": rendered_masks("ball_in_cup.xml", ("cup", "ball")),
        "finger": rendered_masks("finger.xml", ("proximal",)),
    }


def opencv_approximate(mask):
    """The recipe written with OpenCV (the reference tools): values before the threshold."""
    small = cv2.resize(mask.astype(np.float32), (28, 28), interpolation=cv2.INTER_LINEAR)
    big = cv2.resize(small, (84, 84), interpolation=cv2.INTER_LINEAR)
    return cv2.GaussianBlur(big, (0, 0), 0.5)


def dilate3(mask):
    return cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8))


def test_agent_mask_by_hand():
    labels = jnp.array([[LABEL_BACKGROUND, LABEL_FLOOR], [LABEL_AGENT, LABEL_OTHER]])
    np.testing.assert_array_equal(M.agent_mask(labels), [[0, 0], [1, 0]])
    assert M.agent_mask(labels).dtype == jnp.uint8


def test_noisy_mask_drops_about_p(masks):
    mask = jnp.asarray(masks["walker"])  # [60, 84, 84], ~27k agent pixels
    n = int(mask.sum())
    assert n > 10_000
    for p in (0.8, 0.3):
        noisy = np.asarray(M.noisy_mask(mask, jax.random.key(1), p))
        assert not (noisy & (1 - np.asarray(mask))).any(), "never adds a pixel"
        kept = int(noisy.sum())
        # kept ~ Binomial(n, 1 - p): within 4 standard deviations
        std = np.sqrt(n * p * (1 - p))
        assert abs(kept - n * (1 - p)) < 4 * std, (p, kept, n * (1 - p), std)
    np.testing.assert_array_equal(M.noisy_mask(mask, jax.random.key(2), 0.0), mask)
    assert int(M.noisy_mask(mask, jax.random.key(2), 1.0).sum()) == 0


def test_noisy_mask_vmaps_with_independent_keys(masks):
    mask = jnp.asarray(masks["walker"][:4])
    keys = jax.random.split(jax.random.key(0), 4)
    out = jax.jit(jax.vmap(lambda m, k: M.noisy_mask(m, k, 0.5)))(mask, keys)
    assert out.shape == mask.shape and out.dtype == jnp.uint8
    same = jnp.stack([mask[0], mask[0]])
    two = jax.vmap(lambda m, k: M.noisy_mask(m, k, 0.5))(same, keys[:2])
    assert (two[0] != two[1]).any(), "different keys drop different pixels"


@pytest.mark.parametrize("task", ["walker", "cup", "finger"])
def test_approximate_mask_equals_opencv_recipe(masks, task):
    mask = masks[task]
    values = np.asarray(jax.jit(M.approximate_mask_values)(jnp.asarray(mask)))
    ref = np.stack([opencv_approximate(m) for m in mask])
    np.testing.assert_allclose(values, ref, atol=1e-5)
    approx = np.asarray(M.approximate_mask(jnp.asarray(mask)))
    disagree = approx != (ref > 0.9)
    assert (np.abs(ref[disagree] - 0.9) < 1e-5).all(), "only exact ties may differ"


def test_approximate_mask_of_rectangles_is_a_strict_subset():
    """Away from the image border (pixel 0 copies grid sample 1, pixel 83 sample 82)."""
    rng = np.random.default_rng(0)
    for _ in range(300):
        y0, x0 = rng.integers(2, 70, 2)
        h, w = rng.integers(1, 82 - max(y0, x0), 2)
        mask = np.zeros((84, 84), np.uint8)
        mask[y0 : y0 + h, x0 : x0 + w] = 1
        approx = np.asarray(M.approximate_mask(jnp.asarray(mask)))
        assert not (approx & (1 - mask)).any()
        if h >= 9 and w >= 9:
            assert approx.sum() > 0


def test_approximate_mask_fills_a_gap_narrower_than_the_grid():
    """Why it is not a strict subset: a 1-pixel gap between two bars is filled in."""
    mask = np.zeros((84, 84), np.uint8)
    mask[20:60, 20:41] = 1
    mask[20:60, 42:64] = 1  # column 41 stays empty
    approx = np.asarray(M.approximate_mask(jnp.asarray(mask)))
    assert approx[30:50, 41].all()


@pytest.mark.parametrize("task", ["walker", "cup", "finger"])
def test_approximate_mask_on_rendered_masks(masks, task):
    """Eroded: far fewer pixels; outside pixels rare (< 1% of the true mask's) and always
    next to the true mask."""
    mask = masks[task]
    approx = np.asarray(M.approximate_mask(jnp.asarray(mask)))
    extra = approx & (1 - mask)
    assert approx.sum() < 0.7 * mask.sum()
    assert extra.sum() < 0.01 * mask.sum(), (extra.sum(), mask.sum())
    for m, a in zip(mask, approx, strict=True):
        assert not (a & (1 - dilate3(m))).any(), "the proven bound: within one pixel"
    print(task, "true", mask.sum(), "approx", approx.sum(), "outside the true mask", extra.sum())


def test_make_mask_names_valid_kinds():
    labels = jnp.zeros((84, 84), jnp.uint8)
    with pytest.raises(ValueError, match="valid"):
        M.make_mask(labels, jax.random.key(0), "blurry", 0.5)
    # A block of agent pixels: "approximate" is the agent mask through the resize/blur/threshold
    # recipe, which changes it (its edges), and "true" is the agent mask itself.
    labels = labels.at[20:60, 30:50].set(M.LABEL_AGENT)[None, None]
    out = M.make_mask(labels, jax.random.key(0), "approximate", 0.5)
    assert out.shape == (1, 1, 84, 84)
    np.testing.assert_array_equal(out, M.approximate_mask(M.agent_mask(labels)))
    true = M.make_mask(labels, jax.random.key(0), "true", 0.5)
    np.testing.assert_array_equal(true, M.agent_mask(labels))
    assert true.sum() == 40 * 20 and not np.array_equal(out, true)
