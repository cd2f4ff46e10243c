"""DEAR's losses in a model of your own: any encoder whose latent z is split into halves
[z_E, z_A], a mask decoder reading z_A, and whatever loss your agent already has.

    python examples/own_agent.py --steps 300 [--beta 0]

The data here are synthetic so that the example runs in seconds on a CPU: 32 x 32 frames of
noise (the environment) with a bright square (the agent) at a random place, the square's mask,
and as the agent's own task a regression of the square's column from z (a stand-in for a
critic's TD loss). One optimiser step trains encoder, head and decoder on
L = L_task + alpha L_mask + beta L_dis, as DEAR trains encoder, critic and decoder. It prints
the three terms and the mean |cos(z_A, z_E)| as they train; with `--beta 0` the halves stay
correlated.
"""

from __future__ import annotations

import argparse

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from dear_jax import losses

SIZE, SQUARE = 32, 8  # frame side and agent square side, pixels


class Encoder(nn.Module):
    """uint8 frames [B, H, W, 3] -> z [B, latent]."""

    latent: int = 64

    @nn.compact
    def __call__(self, frames):
        x = frames.astype(jnp.float32) / 255.0 - 0.5
        x = nn.relu(nn.Conv(16, (3, 3), strides=2)(x))
        x = nn.relu(nn.Conv(16, (3, 3), strides=2)(x))
        return nn.Dense(self.latent)(x.reshape(x.shape[0], -1))


class MaskDecoder(nn.Module):
    """z_A [B, latent / 2] -> mask logits [B, H, W, 1]."""

    @nn.compact
    def __call__(self, z_agent):
        side = SIZE // 4
        x = nn.relu(nn.Dense(side * side * 16)(z_agent)).reshape(-1, side, side, 16)
        x = nn.relu(nn.ConvTranspose(16, (3, 3), strides=(2, 2))(x))
        return nn.ConvTranspose(1, (3, 3), strides=(2, 2))(x)


class Head(nn.Module):
    """Your agent's own head on the whole latent; here a scalar regression."""

    @nn.compact
    def __call__(self, z):
        return nn.Dense(1)(nn.relu(nn.Dense(64)(z)))[:, 0]


def batch(rng: np.random.Generator, size: int):
    """Frames (noise + one square), the square's mask [B, H, W, 1] and its column in [0, 1]."""
    frames = rng.integers(0, 160, (size, SIZE, SIZE, 3), np.uint8)
    masks = np.zeros((size, SIZE, SIZE, 1), np.uint8)
    top, left = (rng.integers(0, SIZE - SQUARE + 1, size) for _ in range(2))
    for i in range(size):
        rows, cols = slice(top[i], top[i] + SQUARE), slice(left[i], left[i] + SQUARE)
        frames[i, rows, cols] = (255, 220, 60)
        masks[i, rows, cols] = 1
    return frames, masks, (left / (SIZE - SQUARE)).astype(np.float32)


def train(
    steps: int = 300,
    alpha: float = 0.25,
    beta: float = 100.0,
    seed: int = 0,
    batch_size: int = 32,
    log_every: int = 50,
) -> list[dict[str, float]]:
    """Trains the three modules together; returns the metrics every `log_every` steps (and at
    step 0, before any update)."""
    encoder, decoder, head = Encoder(), MaskDecoder(), Head()
    rng = np.random.default_rng(seed)
    frames, _, _ = batch(rng, batch_size)
    k_enc, k_dec, k_head = jax.random.split(jax.random.key(seed), 3)
    params = {
        "encoder": encoder.init(k_enc, frames),
        "decoder": decoder.init(k_dec, jnp.zeros((1, encoder.latent // 2))),
        "head": head.init(k_head, jnp.zeros((1, encoder.latent))),
    }
    optimiser = optax.adam(1e-3)
    opt_state = optimiser.init(params)

    def loss_fn(params, frames, masks, target):
        z = encoder.apply(params["encoder"], frames)
        z_env, z_agent = losses.split_latent(z)
        l_task = jnp.mean(jnp.square(head.apply(params["head"], z) - target))
        l_mask = losses.mask_loss(decoder.apply(params["decoder"], z_agent), masks)
        l_dis = losses.orthogonality_loss(z_agent, z_env)
        metrics = {"task": l_task, "mask": l_mask, "dis": l_dis}
        metrics.update(losses.latent_cosines(z_agent, z_env))
        return l_task + alpha * l_mask + beta * l_dis, metrics

    @jax.jit
    def step(params, opt_state, frames, masks, target):
        grads, metrics = jax.grad(loss_fn, has_aux=True)(params, frames, masks, target)
        updates, opt_state = optimiser.update(grads, opt_state)
        return optax.apply_updates(params, updates), opt_state, metrics

    evaluate = jax.jit(loss_fn)
    history = []
    for i in range(steps + 1):
        frames, masks, target = batch(rng, batch_size)
        if i == steps or i % log_every == 0:  # measured before this step's update
            _, metrics = evaluate(params, frames, masks, target)
            history.append({"step": i, **{k: float(v) for k, v in metrics.items()}})
            row = history[-1]
            print(
                f"step {i:4d}: task {row['task']:.4f}  mask {row['mask']:7.2f}  "
                f"|cos(z_A, z_E)| {row['abs_cos_agent_env']:.4f}"
            )
        if i < steps:
            params, opt_state, _ = step(params, opt_state, frames, masks, target)
    return history


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--alpha", type=float, default=0.25, help="mask loss weight")
    parser.add_argument("--beta", type=float, default=100.0, help="orthogonality loss weight")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    train(args.steps, args.alpha, args.beta, args.seed)


if __name__ == "__main__":
    main()
