"""DEAR's losses in a model of your own: any encoder whose latent z is split into halves
[z_E, z_A], a mask decoder reading z_A, and whatever loss your agent already has.

    python examples/own_agent.py --steps 300 [--beta 0]

The data here are synthetic so that the example runs in seconds on a CPU: 32 x 32 frames of
noise (the environment) with a bright square (the agent) at a random place, the square's mask,
and as the agent's own task a regression of the square's column from z (a stand-in for a
critic's TD loss). One optimiser step trains encoder, head and decoder on
L = L_task + alpha L_mask + beta L_dis, as DEAR trains encoder, critic and decoder
(`dear_jax.update.learner_loss`). It prints L_task, L_mask and L_dis = mean |cos(z_A, z_E)|
(the paper's Table II metric) on a fixed batch as they train, beside what a predictor blind to
the frame scores. Two random halves of this latent have |cos| ~0.14; beta = 100 drives it far
below that, beta = 0 leaves it near. The noise here carries nothing to disentangle: the example
shows the mechanics (shapes, weights, where the gradients go), not the paper's effect.

alpha = 0.25 weighs a mask loss summed over 84 x 84 pixels and 3 frames (DEAR's); for frames of
another size, scale it by the ratio of pixel counts to keep DEAR's balance against its critic
loss (this example, whose task loss is not a critic's, keeps 0.25 on its 32 x 32 x 1 masks).
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


def frame_blind_losses() -> dict[str, float]:
    """The losses of the best predictors that ignore the frame: a mask decoder that gives every
    pixel the agent's share p of the frame (H x W binary entropies of p), and a head that gives
    the mean column (the column's variance). Below them, the model has read the square from z."""
    p = SQUARE**2 / SIZE**2
    n = SIZE - SQUARE  # the square's left column is uniform on 0..n
    mask = -(SIZE**2) * (p * np.log(p) + (1 - p) * np.log1p(-p))
    return {"task": ((n + 1) ** 2 - 1) / 12 / n**2, "mask": float(mask)}


def train(
    steps: int = 300,
    alpha: float = 0.25,
    beta: float = 100.0,
    seed: int = 0,
    batch_size: int = 32,
    log_every: int = 50,
) -> list[dict[str, float]]:
    """Trains the three modules together; returns the metrics on a fixed batch of 128 every
    `log_every` steps, at step 0 (before any update) and at the end."""
    encoder, decoder, head = Encoder(), MaskDecoder(), Head()
    rng = np.random.default_rng(seed)
    k_enc, k_dec, k_head = jax.random.split(jax.random.key(seed), 3)
    params = {
        "encoder": encoder.init(k_enc, jnp.zeros((1, SIZE, SIZE, 3), jnp.uint8)),
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
        # Moves z_A only: z_E is a constant inside (it learns from l_task alone).
        l_dis = losses.orthogonality_loss(z_agent, z_env)
        metrics = {"task": l_task, "mask": l_mask, "dis": l_dis}
        metrics.update(losses.latent_cosines(z_agent, z_env))
        return l_task + alpha * l_mask + beta * l_dis, metrics

    @jax.jit
    def step(params, opt_state, frames, masks, target):
        grads, _ = jax.grad(loss_fn, has_aux=True)(params, frames, masks, target)
        updates, opt_state = optimiser.update(grads, opt_state)
        return optax.apply_updates(params, updates), opt_state

    evaluate = jax.jit(loss_fn)
    held_out = batch(np.random.default_rng([seed, 1]), 128)
    blind = frame_blind_losses()
    print(f"a frame-blind predictor: task {blind['task']:.4f}  mask {blind['mask']:7.2f}")
    history = []
    for i in range(steps + 1):
        if i == steps or i % log_every == 0:  # before this step's update
            _, metrics = evaluate(params, *held_out)
            history.append({"step": i, **{k: float(v) for k, v in metrics.items()}})
            row = history[-1]
            print(
                f"step {i:4d}: task {row['task']:.4f}  mask {row['mask']:7.2f}  "
                f"|cos(z_A, z_E)| {row['abs_cos_agent_env']:.4f}"
            )
        if i < steps:
            params, opt_state = step(params, opt_state, *batch(rng, batch_size))
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
