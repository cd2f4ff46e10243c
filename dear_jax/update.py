"""The DrQ-v2 learner with DEAR's (and SEAR's, TED's) auxiliary losses as pure functions.

`AgentConfig` is static (which method, which encoder, widths, learning rates); `HParams` holds the
numbers that may differ between seeds (loss weights, schedules), so a sweep is one vmapped axis.
`update(state, batch, key, hp)` does, for one seed:
  1. encoder + critic + auxiliary heads in one gradient step on
     L = L_critic + alpha * L_mask + beta * L_dis (+ SEAR's reconstruction, TED's classifier);
  2. the actor step on stopped features against the updated critic;
  3. the target critic's EMA.
`jax.jit(jax.vmap(partial(update, cfg=cfg)))(states, batches, keys, hp.for_seeds(S))` runs S
seeds in one call.
"""

from __future__ import annotations

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from dear_jax import augment, losses, networks, wideconv
from dear_jax.replay import Batch

METHODS = ("drqv2", "dear", "sear", "ted")
MASK_METHODS = ("dear", "sear")  # the methods whose loss reads the agent's mask


@dataclasses.dataclass(frozen=True)
class AgentConfig:
    """Static agent description: changing any field changes the compiled program."""

    action_dim: int
    method: str = "dear"
    encoder: str = "pool"  # "pool" (DEAR/SEAR/TED) or "plain" (DrQ-v2's flattened convs)
    latent_dim: int = 4096  # pool encoder output; split in halves for DEAR and SEAR
    feature_dim: int = 50
    hidden_dim: int = 1024
    lr: float = 1e-4  # encoder, critic, actor and decoders
    ted_lr: float = 1e-3
    ortho_form: str = "abs_cos"  # or "reference_code" (see losses.orthogonality_loss)
    ted_form: str = "strict"  # or "reference_code" (losses.TED_FORMS; docs/method.md, decision 8)
    obs_shape: tuple[int, int, int] = (84, 84, 9)
    frame_stack: int = 3
    augment_pad: int = 4
    # "bfloat16": encoder and decoders compute in bf16; the actor's and critic's products, and
    # their gradients', read bf16 operands (float32 results). Parameters, optimiser and losses
    # stay float32.
    compute_dtype: str = "float32"
    shift_impl: str = "gather"  # how the random shift is computed (augment.SHIFT_IMPLS)
    filter_gradient: str = "cudnn"  # convolutions' filter gradients (networks.FILTER_GRADIENTS)
    conv_stack: str = "auto"  # how the conv stacks run (networks.STACKS; "auto": Pallas on GPUs)
    kernels: str = ""  # the Pallas stacks' constants for the update, "NAME=INT,..." (wideconv)

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; valid: {METHODS}")
        if self.ortho_form not in losses.ORTHOGONALITY_FORMS:
            raise ValueError(
                f"unknown ortho_form {self.ortho_form!r}; valid: {losses.ORTHOGONALITY_FORMS}"
            )
        if self.ted_form not in losses.TED_FORMS:
            raise ValueError(f"unknown ted_form {self.ted_form!r}; valid: {losses.TED_FORMS}")
        if self.compute_dtype not in ("float32", "bfloat16"):
            raise ValueError(
                f"unknown compute_dtype {self.compute_dtype!r}; valid: 'float32', 'bfloat16'"
            )
        if self.shift_impl not in augment.SHIFT_IMPLS:
            raise ValueError(
                f"unknown shift_impl {self.shift_impl!r}; valid: {augment.SHIFT_IMPLS}"
            )
        if self.filter_gradient not in networks.FILTER_GRADIENTS:
            raise ValueError(
                f"unknown filter_gradient {self.filter_gradient!r}; valid: "
                f"{networks.FILTER_GRADIENTS}"
            )
        if self.conv_stack not in networks.STACKS:
            raise ValueError(f"unknown conv_stack {self.conv_stack!r}; valid: {networks.STACKS}")
        wideconv.parse_constants(self.kernels)
        if self.method != "drqv2" and self.encoder != "pool":
            raise ValueError(
                f"method {self.method!r} needs encoder='pool' (its heads read the latent)"
            )

    @property
    def uses_mask(self) -> bool:
        return self.method in MASK_METHODS


@struct.dataclass
class HParams:
    """Per-seed numbers (vmappable). Defaults: docs/method.md, Hyperparameters."""

    alpha: float = 0.25  # mask loss weight (DEAR, SEAR)
    beta: float = 100.0  # orthogonality loss weight (DEAR)
    recon_weight: float = 1.0  # SEAR's reconstruction loss weight
    ted_weight: float = 100.0
    tau: float = 0.01  # target critic EMA rate
    stddev_clip: float = 0.3
    std_init: float = 1.0
    std_final: float = 0.1
    std_steps: float = 500_000.0  # agent steps of the linear std decay
    explore_steps: float = 2000.0  # agent steps of uniform random actions
    # Agent steps each env keeps one exploration draw (its noise, or its uniform action while
    # exploring): 1, DrQ-v2's and the paper's, draws anew every step (`act`).
    noise_hold: float = 1.0

    def for_seeds(self, num_seeds: int) -> HParams:
        """Every field as a float32 [num_seeds] array (scalars broadcast), ready for vmap axis 0."""
        return jax.tree.map(lambda x: jnp.broadcast_to(jnp.float32(x), (num_seeds,)), self)


@struct.dataclass
class AgentState:
    params: dict  # encoder, actor, critic, and per method: mask_decoder, recon_decoder, ted
    target_critic: dict
    opt_state: optax.OptState  # encoder + critic + auxiliary heads: one optimizer, one step
    actor_opt_state: optax.OptState
    steps: jax.Array  # int32: agent steps acted (drives the std schedule and exploration)
    updates: jax.Array  # int32


@dataclasses.dataclass(frozen=True)
class Networks:
    encoder: nn.Module
    actor: nn.Module
    critic: nn.Module
    mask_decoder: nn.Module | None
    recon_decoder: nn.Module | None
    ted: nn.Module | None


def make_networks(cfg: AgentConfig) -> Networks:
    dtype = jnp.dtype(cfg.compute_dtype)
    return Networks(
        encoder=networks.encoder_module(cfg.encoder, cfg.latent_dim, dtype),
        actor=networks.Actor(cfg.action_dim, cfg.feature_dim, cfg.hidden_dim, dtype),
        critic=networks.Critic(cfg.feature_dim, cfg.hidden_dim, dtype),
        mask_decoder=networks.PoolDecoder(cfg.frame_stack, dtype) if cfg.uses_mask else None,
        recon_decoder=(
            networks.PoolDecoder(cfg.obs_shape[-1], dtype, loss="clipped_squares")
            if cfg.method == "sear"
            else None
        ),
        ted=networks.TEDClassifier(cfg.ted_form) if cfg.method == "ted" else None,
    )


def _optimizers(cfg: AgentConfig):
    main = optax.multi_transform(
        {"default": optax.adam(cfg.lr), "ted": optax.adam(cfg.ted_lr)},
        lambda params: {k: ("ted" if k == "ted" else "default") for k in params},
    )
    return main, optax.adam(cfg.lr)


def init_params(cfg: AgentConfig, key: jax.Array) -> dict:
    nets = make_networks(cfg)
    keys = dict(
        zip(("encoder", "actor", "critic", "mask", "recon", "ted"), jax.random.split(key, 6))
    )
    obs = jnp.zeros((1, *cfg.obs_shape), jnp.uint8)
    encoder_params = nets.encoder.init(keys["encoder"], obs)
    z = jnp.zeros(jax.eval_shape(nets.encoder.apply, encoder_params, obs).shape)
    half = z[:, : z.shape[-1] // 2]
    params = {
        "encoder": encoder_params["params"],
        "actor": nets.actor.init(keys["actor"], z)["params"],
        "critic": nets.critic.init(keys["critic"], z, jnp.zeros((1, cfg.action_dim)))["params"],
    }
    if nets.mask_decoder is not None:
        params["mask_decoder"] = nets.mask_decoder.init(keys["mask"], half)["params"]
    if nets.recon_decoder is not None:
        params["recon_decoder"] = nets.recon_decoder.init(keys["recon"], half)["params"]
    if nets.ted is not None:
        params["ted"] = nets.ted.init(keys["ted"], z, z)["params"]
    return params


def init(cfg: AgentConfig, key: jax.Array) -> AgentState:
    """A fresh agent for one seed (vmap over keys for several)."""
    params = init_params(cfg, key)
    main_opt, actor_opt = _optimizers(cfg)
    learner = {k: v for k, v in params.items() if k != "actor"}
    return AgentState(
        params=params,
        target_critic=params["critic"],
        opt_state=main_opt.init(learner),
        actor_opt_state=actor_opt.init(params["actor"]),
        steps=jnp.zeros((), jnp.int32),
        updates=jnp.zeros((), jnp.int32),
    )


def init_seeds(cfg: AgentConfig, keys: jax.Array) -> AgentState:
    """Fresh agents for S seeds from keys [S]: an AgentState whose leaves have a leading [S] axis.

    Seeds are initialised one after another (`lax.map`), not vmapped: a vmapped orthogonal init
    becomes several batched QR calls that XLA:CPU may run at once, and with as few threads as a
    2-core machine has they deadlock (seen with jax 0.10.2). Initialising is a one-off cost.
    """
    return jax.lax.map(functools.partial(init, cfg), keys)


SEED_AXES = ("vmap", "loop", "hybrid")


def over_seeds(fn, how: str = "vmap"):
    """`fn` of one seed applied to every seed of a leading [S] axis, in one traced program.

    how="vmap": `jax.vmap(fn)`. how="loop": one traced call per seed, results stacked.
    how="hybrid": `jax.vmap(fn)` with every convolution unrolled over the seeds
    (`networks.conv_settings(loop_seeds=True)`). All three give the same numbers; they differ in speed only.
    A vmapped convolution whose weights differ per seed becomes one grouped convolution, which
    an H100 ran ~1.5x slower than S plain ones (benchmarks/results/update_h100.json), so GPUs
    loop the convolutions, either alone ("hybrid") or with the whole update ("loop").
    """
    if how == "vmap":
        return jax.vmap(fn)
    if how == "hybrid":
        vmapped = jax.vmap(fn)

        def hybrid(*args):
            with networks.conv_settings(loop_seeds=True):
                return vmapped(*args)

        return hybrid
    if how != "loop":
        raise ValueError(f"unknown seed axis {how!r}; valid: {SEED_AXES}")

    def looped(*args):
        num_seeds = jax.tree.leaves(args)[0].shape[0]
        outs = [fn(*jax.tree.map(lambda x, i=i: x[i], args)) for i in range(num_seeds)]
        return jax.tree.map(lambda *xs: jnp.stack(xs), *outs)

    return looped


def std_schedule(steps: jax.Array, hp: HParams) -> jax.Array:
    """Linear exploration std from std_init to std_final over std_steps agent steps."""
    frac = jnp.clip(steps / hp.std_steps, 0.0, 1.0)
    return hp.std_init + frac * (hp.std_final - hp.std_init)


def sample_action(mean, std, key, clip=None):
    """DrQ-v2's truncated normal: mean + noise (clipped to +-clip if given), clamped to (-1, 1).

    The clamp passes gradients straight through, as in DrQ-v2, so the actor still learns at the
    action bounds.
    """
    noise = std * jax.random.normal(key, mean.shape)
    if clip is not None:
        noise = jnp.clip(noise, -clip, clip)
    x = mean + noise
    eps = 1e-6
    return x + jax.lax.stop_gradient(jnp.clip(x, -1.0 + eps, 1.0 - eps) - x)


def act(
    cfg: AgentConfig,
    state: AgentState,
    obs: jax.Array,
    key: jax.Array,
    hp: HParams,
    *,
    explore: bool,
    stepping: jax.Array | None = None,
    hold_key: jax.Array | None = None,
) -> tuple[jax.Array, AgentState]:
    """Actions for a batch of observations uint8 [N, 84, 84, 9] -> f32 [N, A].

    explore=True: uniform actions during the first `explore_steps` agent steps, then the policy
    with the scheduled std; counts the steps taken: all N, or where `stepping` [N] is true (an
    env that restarts ignores its action). explore=False: the deterministic mean.

    `hold_key` (the seed's, constant over its run) with `hp.noise_hold` = K > 1: the draws come
    from fold_in(hold_key, the block of K agent steps per env this step is in) rather than from
    `key`, so each env keeps its noise (scaled by the current std) or its uniform action for K
    steps: exploration correlated over time. With K = 1, or no `hold_key`, every step draws anew.
    The block follows the seed's steps taken over its N envs: where envs restart (and take no
    step) the blocks of the others last a little longer than K steps.
    """
    nets = make_networks(cfg)
    z = nets.encoder.apply({"params": state.params["encoder"]}, obs)
    mean = nets.actor.apply({"params": state.params["actor"]}, z)
    if not explore:
        return mean, state
    if hold_key is not None:
        per_env = (state.steps // obs.shape[0]).astype(jnp.float32)
        block = jax.random.fold_in(hold_key, (per_env / hp.noise_hold).astype(jnp.uint32))
        data = jnp.where(hp.noise_hold > 1, jax.random.key_data(block), jax.random.key_data(key))
        key = jax.random.wrap_key_data(data, impl=jax.random.key_impl(key))
    k_noise, k_uniform = jax.random.split(key)
    action = sample_action(mean, std_schedule(state.steps, hp), k_noise)
    uniform = jax.random.uniform(k_uniform, mean.shape, minval=-1.0, maxval=1.0)
    action = jnp.where(state.steps < hp.explore_steps, uniform, action)
    taken = obs.shape[0] if stepping is None else jnp.sum(stepping, dtype=jnp.int32)
    return action, state.replace(steps=state.steps + taken)


def learner_loss(
    learner: dict,
    actor_params: dict,
    target_critic: dict,
    batch: Batch,
    key: jax.Array,
    hp: HParams,
    std: jax.Array,
    *,
    cfg: AgentConfig,
    mean_over: str | None = None,
) -> tuple[jax.Array, dict]:
    """Encoder + critic + auxiliary loss of one batch; `learner` is what is differentiated.

    Returns (L, (metrics, z)) with L = L_critic + alpha L_mask + beta L_dis + w_rec L_rec
    + w_ted L_ted, and z the stopped latent of the augmented batch, which the actor step reuses.
    mean_over: as `update`'s (the batch is one part of a batch split over that axis).
    """
    nets = make_networks(cfg)
    k_obs, k_next, k_far, k_target, k_ted = jax.random.split(key, 5)
    # The encoder crops the pixels itself (with Pallas stacks, as it reads them).
    encode = lambda obs, crops: nets.encoder.apply(  # noqa: E731
        {"params": learner["encoder"]}, obs, crops
    )
    crops, next_crops, far_crops = (
        augment.Crops.sample(k, batch.obs.shape[0], cfg.augment_pad, cfg.shift_impl)
        for k in (k_obs, k_next, k_far)
    )

    z = encode(batch.obs, crops)
    z_next = encode(batch.next_obs, next_crops)
    # DrQ-v2 has no target encoder: the target uses the online encoder without gradient.
    z_next_sg = jax.lax.stop_gradient(z_next)
    next_action = sample_action(
        nets.actor.apply({"params": actor_params}, z_next_sg), std, k_target, hp.stddev_clip
    )
    tq1, tq2 = nets.critic.apply({"params": target_critic}, z_next_sg, next_action)
    target = losses.td_target(batch.reward, batch.discount, tq1, tq2)
    q1, q2 = nets.critic.apply({"params": learner["critic"]}, z, batch.action)
    critic = losses.critic_loss(q1, q2, target)

    z_env, z_agent = losses.split_latent(z)
    metrics = {
        "critic_loss": critic,
        "q1": jnp.mean(q1),
        "q2": jnp.mean(q2),
        "target_q": jnp.mean(target),
        "batch_reward": jnp.mean(batch.reward),
        **losses.latent_cosines(z_agent, z_env),
    }
    total = critic
    # The decoders' losses are sums over pixels, taken over the decoders' output phases (the
    # targets laid out alike): the same values, and no interleaving of outputs and gradients.
    if cfg.uses_mask:
        # The decoder takes the loss's target: with Pallas stacks, its last kernel computes the
        # loss and its gradient with the logits (which are never written).
        params = {"params": learner["mask_decoder"]}
        l_mask = nets.mask_decoder.apply(params, z_agent, target=(batch.mask, crops))
        metrics["mask_loss"] = l_mask
        total = total + hp.alpha * l_mask
    if cfg.method == "dear":
        l_dis = losses.orthogonality_loss(z_agent, z_env, cfg.ortho_form)
        metrics["ortho_loss"] = l_dis
        total = total + hp.beta * l_dis
    if cfg.method == "sear":
        # As the mask decoder: the reconstruction error against the cropped frames, fused
        # into the last kernel with Pallas stacks.
        params = {"params": learner["recon_decoder"]}
        l_rec = nets.recon_decoder.apply(params, z_env, target=(batch.obs, crops))
        metrics["recon_loss"] = l_rec
        total = total + hp.recon_weight * l_rec
    if cfg.method == "ted":
        # Only z_t carries the encoder's gradient: as in TED's reference, the next and the
        # same-episode observations are encoded without gradient (which also spares their
        # backward passes through the encoder).
        z_far = jax.lax.stop_gradient(encode(batch.far_obs, far_crops))
        l_ted, ted_metrics = ted_classifier_loss(
            learner["ted"],
            z,
            z_next_sg,
            z_far,
            batch.far_valid,
            k_ted,
            nets=nets,
            mean_over=mean_over,
            substitute=cfg.ted_form == "reference_code",
        )
        metrics.update(ted_metrics, ted_loss=l_ted)
        total = total + hp.ted_weight * l_ted
    metrics["loss"] = total
    return total, (metrics, jax.lax.stop_gradient(z))


def ted_classifier_loss(
    ted_params,
    z,
    z_next,
    z_far,
    far_valid,
    key,
    *,
    nets: Networks,
    mean_over=None,
    substitute: bool = False,
):
    """TED's temporal loss on latents [B, F]: positives (z_t, z_t+n); negatives (z_t, z_t+n of
    another sample: the next in a shuffle's cycle; substitute: of the shuffled sample) and (z_t, a frame of the same episode, where far_valid [B] is 1:
    `replay.same_episode_offsets`). Mean BCE over the valid pairs; returns (loss, metrics).
    substitute: where far_valid is 0, the pair takes instead of being dropped the frame drawn for
    another sample, the next in the shuffle's cycle (its same-episode frame, or where it has
    none its own at t), as TED's code falls back to another episode's frame. mean_over: a mapped axis over which the
    batch is split in equal parts (its mean over the axis is the whole batch's loss: the valid
    pairs are counted over it; the other-sample negatives are drawn within each part)."""
    perm = jax.random.permutation(key, z.shape[0])
    other = jnp.zeros_like(perm).at[perm].set(jnp.roll(perm, -1))  # perm[p] takes perm[p + 1]'s
    if substitute:
        z_far = jnp.where(far_valid[:, None] > 0, z_far, z_far[other])
        far_valid = jnp.ones_like(far_valid)
    # Strict: another sample's z_t+n, never a sample's own (its positive); TED's code shuffles,
    # which leaves a few in place.
    negatives = z_next[perm] if substitute else z_next[other]
    classify = lambda a, b: nets.ted.apply({"params": ted_params}, a, b)  # noqa: E731
    logits = jnp.concatenate([classify(z, z_next), classify(z, negatives), classify(z, z_far)])
    n = z.shape[0]
    labels = jnp.concatenate([jnp.ones(n), jnp.zeros(2 * n)])
    weights = jnp.concatenate([jnp.ones(2 * n), far_valid])
    loss = losses.ted_loss(logits, labels, weights)
    count = jnp.sum(weights)
    if mean_over is not None:
        # Each part's sum over the pairs divided by the parts' mean count of them: the mean
        # over the axis is then the whole batch's weighted mean.
        mean_count = jax.lax.pmean(count, mean_over)
        loss, count = loss * count / mean_count, mean_count
    acc = jnp.sum(weights * ((logits > 0) == (labels > 0.5))) / count
    return loss, {"ted_accuracy": acc}


def actor_loss(
    actor_params: dict,
    critic_params: dict,
    z: jax.Array,
    key,
    hp: HParams,
    std,
    *,
    cfg: AgentConfig,
):
    """DrQ-v2's actor loss on stopped features: -min(Q1, Q2)(z, a ~ pi(z))."""
    nets = make_networks(cfg)
    mean = nets.actor.apply({"params": actor_params}, z)
    action = sample_action(mean, std, key, hp.stddev_clip)
    q1, q2 = nets.critic.apply({"params": critic_params}, z, action)
    loss = losses.actor_loss(q1, q2)
    return loss, {"actor_loss": loss}


def update(
    state: AgentState,
    batch: Batch,
    key: jax.Array,
    hp: HParams,
    *,
    cfg: AgentConfig,
    mean_over: str | None = None,
) -> tuple[AgentState, dict]:
    """One DrQ-v2 update for one seed; bind `cfg` (functools.partial) before jit/vmap.

    mean_over: a mapped axis (shard_map's) whose members each hold an equal part of the seed's
    batch: the gradients and metrics are averaged over it (`lax.pmean`), so every member takes
    the step of the whole batch and the states stay equal."""
    with (
        networks.conv_settings(filter_gradient=cfg.filter_gradient, stack=cfg.conv_stack),
        wideconv.constants(cfg.kernels),
    ):
        return _update(state, batch, key, hp, cfg, mean_over)


def _update(state, batch, key, hp, cfg, mean_over=None):
    mean = (lambda x: x) if mean_over is None else (lambda x: jax.lax.pmean(x, mean_over))
    main_opt, actor_opt = _optimizers(cfg)
    k_learner, k_actor = jax.random.split(key)
    std = std_schedule(state.steps, hp)
    learner = {k: v for k, v in state.params.items() if k != "actor"}

    grads, (metrics, z) = jax.grad(learner_loss, has_aux=True)(
        learner,
        state.params["actor"],
        state.target_critic,
        batch,
        k_learner,
        hp,
        std,
        cfg=cfg,
        mean_over=mean_over,
    )
    grads, metrics = mean((grads, metrics))
    updates, opt_state = main_opt.update(grads, state.opt_state, learner)
    learner = optax.apply_updates(learner, updates)

    # The actor learns from the stopped features of the pre-update encoder, as in DrQ-v2: the
    # encoder is shaped by the critic and the auxiliary losses only.
    actor_grads, actor_metrics = jax.grad(actor_loss, has_aux=True)(
        state.params["actor"], learner["critic"], z, k_actor, hp, std, cfg=cfg
    )
    actor_grads, actor_metrics = mean((actor_grads, actor_metrics))
    actor_updates, actor_opt_state = actor_opt.update(actor_grads, state.actor_opt_state)
    actor_params = optax.apply_updates(state.params["actor"], actor_updates)

    target = optax.incremental_update(learner["critic"], state.target_critic, hp.tau)
    new_state = state.replace(
        params={**learner, "actor": actor_params},
        target_critic=target,
        opt_state=opt_state,
        actor_opt_state=actor_opt_state,
        updates=state.updates + 1,
    )
    return new_state, {**metrics, **actor_metrics, "std": std}
