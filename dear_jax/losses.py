"""DEAR's losses and the baselines' losses as pure functions of arrays.

Import these into any JAX agent: none needs a config object or a network. Every function works
under `jax.jit`, `jax.vmap` and `jax.grad`. Shapes: B is the batch, F the latent width,
H x W the image, K stacked frames. Reductions follow docs/method.md (Losses) and are part of the contract
(the mask loss is a *sum* over pixels and frames, averaged over the batch).
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import optax

ORTHOGONALITY_FORMS = ("abs_cos", "reference_code")
# TED as dear_jax runs it ("strict") or as TED's code does ("reference_code"): docs/method.md,
# decision 8; `replay.same_episode_offsets`, `update.ted_classifier_loss`, `networks.TEDClassifier`.
TED_FORMS = ("strict", "reference_code")
_COS_EPS = 1e-8


def split_latent(z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """z [..., F] -> (z_env [..., F/2], z_agent [..., F/2]): the first half is the environment's.
    Mind the order: `orthogonality_loss` and `latent_cosines` take (z_agent, z_env)."""
    f = z.shape[-1]
    if f % 2:
        raise ValueError(f"latent width must be even to split into halves, got {f}")
    return z[..., : f // 2], z[..., f // 2 :]


def mask_loss(logits: jax.Array, mask: jax.Array) -> jax.Array:
    """Binary cross-entropy of the agent-mask decoder, from logits.

    L = mean_b sum_{h,w,k} BCE(sigmoid(logits[b,h,w,k]), mask[b,h,w,k])
    logits: float [B, H, W, K], the decoder's output before any sigmoid; mask: {0, 1} (any
    dtype; values in [0, 1] for a soft mask: a 0/255 image must be divided by 255)
    [B, H, W, K]. Rank 4 is checked: give one image a batch axis of 1, and map extra
    leading axes (seeds) with jax.vmap. Computed in float32 whatever the logits' dtype.
    Returns a scalar.
    """
    chex.assert_equal_shape([logits, mask])
    chex.assert_rank(logits, 4)
    logits = logits.astype(jnp.float32)
    bce = sigmoid_cross_entropy(logits, mask.astype(jnp.float32))
    return jnp.mean(jnp.sum(bce.reshape(bce.shape[0], -1), axis=-1))


@jax.custom_vjp
def sigmoid_cross_entropy(logits: jax.Array, labels: jax.Array) -> jax.Array:
    """Elementwise BCE(sigmoid(logits), labels) = softplus(logits) - logits * labels: the values
    of `optax.sigmoid_binary_cross_entropy`. Its gradient, (sigmoid(logits) - labels) for the
    logits, is computed from the inputs alone: autodiff of optax's form keeps two float32 arrays
    of the logits' size for the backward pass (0.3 ms of a 5-seed DEAR update on an H100).
    Reverse mode only (jax.grad, jax.vjp): a custom VJP has no forward-mode rule."""
    return jax.nn.softplus(logits) - logits * labels


def _sigmoid_cross_entropy_fwd(logits, labels):
    return sigmoid_cross_entropy(logits, labels), (logits, labels)


def _sigmoid_cross_entropy_bwd(residuals, g):
    logits, labels = residuals
    return g * (jax.nn.sigmoid(logits) - labels), -g * logits


sigmoid_cross_entropy.defvjp(_sigmoid_cross_entropy_fwd, _sigmoid_cross_entropy_bwd)


def cosine_similarity(a: jax.Array, b: jax.Array) -> jax.Array:
    """Cosine similarity along the last axis: [..., F] x [..., F] -> [...].

    Computed in float32 whatever the inputs' dtype (in bf16 or float16, |cos| of a vector with
    itself may pass 1). Each norm is at least _COS_EPS, clamped before its square root as
    PyTorch's `F.cosine_similarity` clamps them (the reference code's), so a zero vector gives
    a cosine of 0 and a finite gradient, though a large one: b / (eps |b|) for a zero row a.
    """
    a, b = a.astype(jnp.float32), b.astype(jnp.float32)

    def norm(x):
        return jnp.sqrt(jnp.maximum(jnp.sum(x * x, axis=-1), _COS_EPS**2))

    return jnp.sum(a * b, axis=-1) / (norm(a) * norm(b))


def latent_cosines(z_agent: jax.Array, z_env: jax.Array) -> dict[str, jax.Array]:
    """Diagnostics of how far apart the latent halves are ([B, F/2] x 2), batch means of the
    cosine and of its magnitude: signed values of both signs cancel in the first, not the second
    (the metric of the paper's Table II). Values only: no gradient flows from them (the loss is
    `orthogonality_loss`)."""
    cos = cosine_similarity(jax.lax.stop_gradient(z_agent), jax.lax.stop_gradient(z_env))
    return {"cos_agent_env": jnp.mean(cos), "abs_cos_agent_env": jnp.mean(jnp.abs(cos))}


def orthogonality_loss(z_agent: jax.Array, z_env: jax.Array, form: str = "abs_cos") -> jax.Array:
    """DEAR's disentanglement loss between the two halves of the latent; [B, F/2] x 2 -> scalar.

    form="abs_cos" (the paper, default): mean_b |cos(z_agent, sg(z_env))|.
    form="reference_code" (the public code): mean_b (1 - cos(sg(z_env), z_agent)).
    The environment half is a fixed target: the gradient reaches z_agent only.
    """
    chex.assert_equal_shape([z_agent, z_env])
    # DEAR stops the gradient at z_E so that only the agent half is pushed away from it.
    cos = cosine_similarity(z_agent, jax.lax.stop_gradient(z_env))
    if form == "abs_cos":
        return jnp.mean(jnp.abs(cos))
    if form == "reference_code":
        return jnp.mean(1.0 - cos)
    raise ValueError(f"unknown orthogonality form {form!r}; valid: {ORTHOGONALITY_FORMS}")


def reconstruction_loss(recon: jax.Array, obs: jax.Array) -> jax.Array:
    """SEAR's image reconstruction loss.

    L = mean_b sum_{h,w,c} (clip(recon, -0.5, 0.5) - (obs / 255 - 0.5))^2
    recon: float [B, H, W, C] in the [-0.5, 0.5] pixel scale; obs: uint8 [B, H, W, C]. Rank 4
    is checked, as `mask_loss`'s; computed in float32.
    """
    chex.assert_equal_shape([recon, obs])
    chex.assert_rank(recon, 4)
    if not jnp.issubdtype(obs.dtype, jnp.integer):
        raise ValueError(f"obs must be integer pixels in 0-255 (uint8), got {obs.dtype}")
    recon = recon.astype(jnp.float32)
    target = obs.astype(jnp.float32) / 255.0 - 0.5
    err = jnp.square(jnp.clip(recon, -0.5, 0.5) - target)
    return jnp.mean(jnp.sum(err.reshape(err.shape[0], -1), axis=-1))


def ted_loss(logits: jax.Array, labels: jax.Array, weights: jax.Array | None = None) -> jax.Array:
    """TED's temporal classification loss: binary cross-entropy from logits, averaged over the
    pairs, [N] x [N] -> scalar. `weights` [N] (e.g. 0 for a pair that does not exist, such as a
    same-episode negative in an episode too short for one) make it sum(w * BCE) / sum(w), 0
    where every weight is 0. Computed in float32 whatever the logits' dtype."""
    chex.assert_equal_shape([logits, labels])
    logits = logits.astype(jnp.float32)
    bce = optax.sigmoid_binary_cross_entropy(logits, labels.astype(jnp.float32))
    if weights is None:
        return jnp.mean(bce)
    chex.assert_equal_shape([logits, weights])
    total = jnp.sum(weights)
    return jnp.sum(weights * bce) / jnp.where(total > 0, total, 1.0)


def td_target(
    reward: jax.Array, discount: jax.Array, next_q1: jax.Array, next_q2: jax.Array
) -> jax.Array:
    """n-step clipped double-Q target y = R_n + gamma_n * min(Q1', Q2'), all [B] (squeeze a
    critic head's [B, 1] first: shapes that differ are refused rather than broadcast).

    `discount` is the product gamma^n * prod(env discounts) over the n steps. The target is a
    constant for the critic (stop_gradient).
    """
    chex.assert_equal_shape([reward, discount, next_q1, next_q2])
    return jax.lax.stop_gradient(reward + discount * jnp.minimum(next_q1, next_q2))


def critic_loss(q1: jax.Array, q2: jax.Array, target: jax.Array) -> jax.Array:
    """DrQ-v2's twin critic loss: MSE(Q1, y) + MSE(Q2, y), all [B] -> scalar."""
    chex.assert_equal_shape([q1, q2, target])
    return jnp.mean(jnp.square(q1 - target)) + jnp.mean(jnp.square(q2 - target))


def actor_loss(q1: jax.Array, q2: jax.Array) -> jax.Array:
    """DrQ-v2's actor loss: -mean(min(Q1, Q2)) at the policy's sampled action, [B] x 2 -> scalar."""
    chex.assert_equal_shape([q1, q2])
    return -jnp.mean(jnp.minimum(q1, q2))
