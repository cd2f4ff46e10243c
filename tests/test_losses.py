"""Loss values against hand-worked examples, and where gradients may and may not flow."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from dear_jax import losses


def test_split_latent_halves():
    z = jnp.arange(8.0).reshape(2, 4)
    env, agent = losses.split_latent(z)
    np.testing.assert_array_equal(env, [[0, 1], [4, 5]])
    np.testing.assert_array_equal(agent, [[2, 3], [6, 7]])
    with pytest.raises(ValueError, match="even"):
        losses.split_latent(jnp.zeros((2, 3)))


def test_mask_loss_sums_pixels_and_frames_then_averages_batch():
    # Sample 0: logit 0 on a 1 -> ln 2; logit ln 3 (p = 3/4) on a 0 -> ln 4.
    # Sample 1: logit 0 on a 0 -> ln 2; logit -ln 3 (p = 1/4) on a 1 -> ln 4.
    logits = jnp.array([[0.0, math.log(3)], [0.0, -math.log(3)]]).reshape(2, 1, 1, 2)
    mask = jnp.array([[1, 0], [0, 1]], jnp.uint8).reshape(2, 1, 1, 2)
    expected = ((math.log(2) + math.log(4)) + (math.log(2) + math.log(4))) / 2
    np.testing.assert_allclose(losses.mask_loss(logits, mask), expected, rtol=1e-6)


def test_mask_loss_scales_with_pixels_not_batch():
    logits = jnp.zeros((4, 84, 84, 3))
    mask = jnp.ones((4, 84, 84, 3))
    np.testing.assert_allclose(losses.mask_loss(logits, mask), 84 * 84 * 3 * math.log(2), rtol=1e-5)
    # bf16 logits are summed in float32: a bf16 sum of 21,168 terms of ln 2 is ~0.1% off.
    np.testing.assert_allclose(
        losses.mask_loss(logits.astype(jnp.bfloat16), mask), 84 * 84 * 3 * math.log(2), rtol=1e-5
    )
    # A batch axis is required: one image's pixels would otherwise be averaged as a batch.
    with pytest.raises(AssertionError, match="rank"):
        losses.mask_loss(logits[0], mask[0])


def test_mask_loss_gradient_is_sigmoid_minus_mask_over_batch():
    """d L / d logit = (sigmoid(logit) - mask) / B, by hand at logits 0 and +-ln 3, and the
    values and gradients of optax's form (whose autodiff the loss's own backward replaces) from
    -50 to 50, where a naive log(sigmoid) would overflow."""
    logits = jnp.array([[0.0, math.log(3)], [0.0, -math.log(3)]]).reshape(2, 1, 1, 2)
    mask = jnp.array([[1, 0], [0, 1]], jnp.uint8).reshape(2, 1, 1, 2)
    got = jax.grad(losses.mask_loss)(logits, mask)
    want = jnp.array([[0.5 - 1, 0.75], [0.5, 0.25 - 1]]).reshape(2, 1, 1, 2) / 2
    np.testing.assert_allclose(got, want, rtol=1e-6)

    x = jnp.linspace(-50.0, 50.0, 41)
    for y in (jnp.zeros_like(x), jnp.ones_like(x), jnp.full_like(x, 0.3)):
        ours = lambda x, y: jnp.sum(losses.sigmoid_cross_entropy(x, y))  # noqa: E731
        theirs = lambda x, y: jnp.sum(optax.sigmoid_binary_cross_entropy(x, y))  # noqa: E731
        np.testing.assert_allclose(
            losses.sigmoid_cross_entropy(x, y),
            optax.sigmoid_binary_cross_entropy(x, y),
            rtol=1e-6,
            atol=1e-6,
        )
        for a, b in zip(jax.grad(ours, (0, 1))(x, y), jax.grad(theirs, (0, 1))(x, y)):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)


def test_orthogonality_loss_forms():
    z_agent = jnp.array([[1.0, 0.0], [1.0, 0.0]])
    z_env = jnp.array([[1.0, 1.0], [-2.0, 0.0]])  # cos = 1/sqrt(2), then -1
    c = 1 / math.sqrt(2)
    np.testing.assert_allclose(losses.orthogonality_loss(z_agent, z_env), (c + 1) / 2, rtol=1e-6)
    np.testing.assert_allclose(
        losses.orthogonality_loss(z_agent, z_env, "reference_code"), ((1 - c) + 2) / 2, rtol=1e-6
    )
    with pytest.raises(ValueError, match="abs_cos"):
        losses.orthogonality_loss(z_agent, z_env, "cosine")


def test_latent_cosines_signed_mean_cancels_magnitude_does_not():
    z_agent = jnp.array([[1.0, 0.0], [1.0, 0.0]])
    z_env = jnp.array([[1.0, 1.0], [-1.0, 1.0]])  # cos = 1/sqrt(2), then -1/sqrt(2)
    cosines = losses.latent_cosines(z_agent, z_env)
    assert float(cosines["cos_agent_env"]) == pytest.approx(0.0, abs=1e-7)
    assert float(cosines["abs_cos_agent_env"]) == pytest.approx(1 / math.sqrt(2), rel=1e-6)
    # Diagnostics only: added to a loss by mistake, they train neither half.
    grads = jax.grad(lambda a, e: losses.latent_cosines(a, e)["abs_cos_agent_env"], (0, 1))(
        z_agent, z_env
    )
    assert all(np.all(np.asarray(g) == 0.0) for g in grads)


def test_orthogonality_loss_is_zero_for_orthogonal_halves():
    z_agent = jnp.array([[0.0, 3.0, 0.0]])
    z_env = jnp.array([[2.0, 0.0, -1.0]])
    assert float(losses.orthogonality_loss(z_agent, z_env)) == 0.0


@pytest.mark.parametrize("form", losses.ORTHOGONALITY_FORMS)
def test_a_zero_latent_row_gives_cosine_zero_and_a_finite_gradient(form):
    """A zero row (a ReLU latent, a padded sample): its cosine is 0 and every gradient finite,
    each norm clamped at eps as PyTorch's `F.cosine_similarity` clamps them (the reference's
    loss), so the zero row's gradient is b / (eps |b|) over the batch."""
    z_agent = jnp.array([[0.0, 0.0], [1.0, 0.0]])
    z_env = jnp.array([[1.0, 1.0], [1.0, 1.0]])  # row 1: cos = 1/sqrt(2)
    np.testing.assert_allclose(losses.cosine_similarity(z_agent, z_env), [0.0, 2**-0.5], rtol=1e-6)
    g = jax.grad(losses.orthogonality_loss)(z_agent, z_env, form)
    assert np.all(np.isfinite(np.asarray(g)))
    # d cos / d a = b / (|a||b|) - cos a / |a|^2 = (1, 1)/sqrt(2) - (1, 0)/sqrt(2) = (0, 1/sqrt(2)),
    # halved by the batch mean; the abs form's sign is cos's (+), the reference form's is -.
    sign = 1.0 if form == "abs_cos" else -1.0
    np.testing.assert_allclose(np.asarray(g)[1], [0.0, sign * 2**-0.5 / 2], rtol=1e-6, atol=1e-7)
    zero_row = np.array([1.0, 1.0]) / (losses._COS_EPS * math.sqrt(2)) / 2
    np.testing.assert_allclose(np.asarray(g)[0], sign * zero_row, rtol=1e-6)


@pytest.mark.parametrize("form", losses.ORTHOGONALITY_FORMS)
def test_orthogonality_gradient_reaches_agent_half_only(form):
    key_a, key_e = jax.random.split(jax.random.key(0))
    z_agent = jax.random.normal(key_a, (5, 16))
    z_env = jax.random.normal(key_e, (5, 16))
    g_agent, g_env = jax.grad(losses.orthogonality_loss, argnums=(0, 1))(z_agent, z_env, form)
    assert np.all(np.asarray(g_env) == 0.0)
    assert np.abs(np.asarray(g_agent)).sum() > 0


def test_orthogonality_through_a_full_latent():
    """Differentiating w.r.t. the whole z = [z_E, z_A]: only the agent half moves."""
    z = jax.random.normal(jax.random.key(1), (3, 8))

    def loss(z):
        z_env, z_agent = losses.split_latent(z)
        return losses.orthogonality_loss(z_agent, z_env)

    g = np.asarray(jax.grad(loss)(z))
    assert np.all(g[:, :4] == 0.0) and np.abs(g[:, 4:]).sum() > 0


def test_reconstruction_loss_clips_prediction_and_scales_target():
    obs = jnp.array([0, 255], jnp.uint8).reshape(1, 1, 1, 2)  # targets -0.5 and 0.5
    recon = jnp.array([0.0, 2.0]).reshape(1, 1, 1, 2)  # 2.0 is clipped to 0.5
    np.testing.assert_allclose(losses.reconstruction_loss(recon, obs), 0.25, rtol=1e-6)
    # Against targets of -0.5: 0 -> 0.25, 2.0 clipped to 0.5 -> 1.0; the clip stops the gradient
    # of the out-of-range prediction (2 (0 + 0.5) = 1 for the other; 2 (2 + 0.5) = 5 unclipped).
    dark = jnp.zeros((1, 1, 1, 2), jnp.uint8)
    np.testing.assert_allclose(losses.reconstruction_loss(recon, dark), 1.25, rtol=1e-6)
    g = jax.grad(losses.reconstruction_loss)(recon, dark)
    np.testing.assert_array_equal(np.asarray(g).ravel(), [1.0, 0.0])
    # Pixels given as floats in [0, 1] would be scaled as if 0-255: refused, naming the dtype.
    with pytest.raises(ValueError, match="integer pixels in 0-255.*float32"):
        losses.reconstruction_loss(recon, dark.astype(jnp.float32) / 255.0)


def test_ted_loss_is_mean_bce_and_weights_drop_pairs():
    logits = jnp.array([0.0, math.log(3), math.log(3)])
    labels = jnp.array([1.0, 1.0, 0.0])  # ln 2, -ln(3/4) = ln(4/3), -ln(1/4) = ln 4
    np.testing.assert_allclose(
        losses.ted_loss(logits, labels),
        (math.log(2) + math.log(4 / 3) + math.log(4)) / 3,
        rtol=1e-6,
    )
    weights = jnp.array([1.0, 0.0, 1.0])  # the second pair does not exist
    np.testing.assert_allclose(
        losses.ted_loss(logits, labels, weights), (math.log(2) + math.log(4)) / 2, rtol=1e-6
    )
    # No pair at all: 0 and a zero gradient, not 0 / 0.
    loss, g = jax.value_and_grad(losses.ted_loss)(logits, labels, jnp.zeros(3))
    assert float(loss) == 0.0 and np.all(np.asarray(g) == 0.0)
    # bf16 logits are taken in float32: the float32 loss of the same (bf16-representable) values.
    half = losses.ted_loss(logits.astype(jnp.bfloat16), labels)
    assert half.dtype == jnp.float32
    np.testing.assert_allclose(
        half, losses.ted_loss(logits.astype(jnp.bfloat16).astype(float), labels), rtol=1e-6
    )


def test_cosine_is_taken_in_float32_whatever_the_inputs_dtype():
    """bf16 and float16 latents: the cosine of their values in float32, so |cos(x, x)| is 1
    within float32 rounding (in bf16 it came out 1.0078) and a float16 zero row is 0, not NaN
    (its squared eps underflows in float16)."""
    x = jax.random.normal(jax.random.key(3), (4, 64))
    for dtype in (jnp.bfloat16, jnp.float16):
        h = x.astype(dtype)
        cos = losses.cosine_similarity(h, h)
        assert cos.dtype == jnp.float32
        np.testing.assert_allclose(cos, 1.0, rtol=1e-6)
        zero = losses.cosine_similarity(jnp.zeros((1, 64), dtype), h[:1])
        assert float(zero[0]) == 0.0


def test_td_target_and_critic_loss():
    # Sample 0 takes Q1' (the lower), sample 2 Q2' (the lower); sample 1 ends its episode.
    y = losses.td_target(
        jnp.array([1.0, 0.5, 0.0]),
        jnp.array([0.99, 0.0, 0.5]),
        jnp.array([2.0, 5.0, 3.0]),
        jnp.array([3.0, 1.0, 2.0]),
    )
    np.testing.assert_allclose(y, [1.0 + 0.99 * 2.0, 0.5, 0.5 * 2.0], rtol=1e-6)
    y = y[:2]
    q1, q2 = jnp.array([3.0, 0.5]), jnp.array([2.98, 1.5])
    expected = ((3.0 - 2.98) ** 2 + 0.0) / 2 + (0.0 + 1.0) / 2
    np.testing.assert_allclose(losses.critic_loss(q1, q2, y), expected, rtol=1e-5)
    # A critic head's [B, 1] is refused, not broadcast against [B] rewards into [B, B].
    with pytest.raises(AssertionError, match="shape"):
        losses.td_target(jnp.ones(2), jnp.ones(2), jnp.ones((2, 1)), jnp.ones((2, 1)))
    # The target is a constant for the critic.
    g = jax.grad(lambda nq: losses.td_target(jnp.ones(2), jnp.ones(2), nq, nq).sum())(jnp.ones(2))
    assert np.all(np.asarray(g) == 0.0)


def test_actor_loss_is_negative_min_q():
    np.testing.assert_allclose(
        losses.actor_loss(jnp.array([1.0, 4.0]), jnp.array([2.0, 3.0])), -(1.0 + 3.0) / 2
    )


def test_losses_under_jit_and_vmap():
    key = jax.random.key(2)
    logits = jax.random.normal(key, (3, 4, 2, 2, 3))  # 3 seeds, batch 4
    mask = (logits > 0).astype(jnp.uint8)
    per_seed = jax.jit(jax.vmap(losses.mask_loss))(logits, mask)
    for s in range(3):
        np.testing.assert_allclose(per_seed[s], losses.mask_loss(logits[s], mask[s]), rtol=1e-6)
    z = jax.random.normal(key, (3, 4, 8))
    ortho = jax.jit(jax.vmap(losses.orthogonality_loss))(z[..., 4:], z[..., :4])
    assert ortho.shape == (3,)
    for s in range(3):
        np.testing.assert_allclose(
            ortho[s], losses.orthogonality_loss(z[s, :, 4:], z[s, :, :4]), rtol=1e-6
        )
