"""The learner: where gradients flow, acting, and the vmapped update over seeds."""

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dear_jax import augment, lanes, losses, update
from dear_jax.replay import Batch

# Narrow widths keep CPU compile and init cheap; the structure is the reference's.
SMALL = dict(action_dim=2, latent_dim=64, hidden_dim=32, feature_dim=8)
B = 4


def _batches(seeds, far=False, stacked=True) -> Batch:
    """A random batch per seed, stacked on a leading seeds axis (or the first seed's alone),
    drawn with NumPy: jax.random compiles a program per shape, several seconds each for the
    image-sized ones."""
    rngs = [np.random.default_rng(s) for s in seeds]

    def draw(fn):
        x = np.stack([fn(rng) for rng in rngs])
        return jnp.asarray(x if stacked else x[0])

    img = lambda rng: rng.integers(0, 256, (B, 84, 84, 9), np.uint8)  # noqa: E731
    return Batch(
        obs=draw(img),
        action=draw(lambda rng: rng.uniform(-1, 1, (B, 2)).astype(np.float32)),
        reward=draw(lambda rng: rng.uniform(0, 1, B).astype(np.float32)),
        discount=draw(lambda rng: np.full(B, 0.99, np.float32)),
        next_obs=draw(img),
        mask=draw(lambda rng: (rng.uniform(size=(B, 84, 84, 3)) > 0.7).astype(np.uint8)),
        far_obs=draw(img) if far else None,
        far_valid=draw(lambda rng: np.ones(B, np.float32)) if far else None,
    )


def _batch(seed: int, far=False) -> Batch:
    return _batches([seed], far, stacked=False)


@pytest.mark.parametrize(
    "method, weight, decoder, half",
    [
        ("dear", "alpha", "mask_decoder", "agent"),
        ("sear", "alpha", "mask_decoder", "agent"),
        ("sear", "recon_weight", "recon_decoder", "env"),
    ],
)
def test_a_decoders_loss_reaches_only_its_half(method, weight, decoder, half):
    """Through the update's own loss (`update.learner_loss`): a decoder's term (the gradient
    with its weight 1 less the one with weight 0, the loss being linear in it) reaches the
    decoder and the encoder's output columns of its half of z, and not one column of the other:
    the mask decoder reads z_A, SEAR's reconstruction decoder z_E. The encoder's last layer is
    a Dense whose kernel columns are z's coordinates, z_E the first half."""
    cfg = update.AgentConfig(method=method, **SMALL)
    state = _init(cfg, jax.random.key(0))
    learner = {k: v for k, v in state.params.items() if k != "actor"}
    batch = _batch(1)

    @jax.jit
    def grads(hp):
        loss = functools.partial(update.learner_loss, cfg=cfg)
        return jax.grad(
            lambda p: loss(
                p,
                state.params["actor"],
                state.target_critic,
                batch,
                jax.random.key(2),
                hp,
                jnp.float32(0.5),
            )[0]
        )(learner)

    on, off = (grads(update.HParams(beta=0.0, **{weight: w})) for w in (1.0, 0.0))
    term = jax.tree.map(lambda a, b: np.asarray(a - b), on, off)
    kernel = term["encoder"]["Dense_0"]["kernel"]
    size = kernel.shape[-1] // 2
    env_cols, agent_cols = kernel[:, :size], kernel[:, size:]
    read, other = (agent_cols, env_cols) if half == "agent" else (env_cols, agent_cols)
    assert np.all(other == 0.0) and np.abs(read).sum() > 0
    assert all(np.abs(g).sum() > 0 for g in jax.tree.leaves(term[decoder]))
    assert all(np.all(g == 0) for g in jax.tree.leaves(term["critic"]))


@functools.cache
def _jitted_update(cfg: update.AgentConfig):
    """The jitted update of `cfg`, one per config for the whole file: a new jax.jit of the same
    function compiles it again (~15 s)."""
    return jax.jit(functools.partial(update.update, cfg=cfg))


# One jitted init for the file (eager, each of its operations compiles on its own).
_init = jax.jit(update.init, static_argnums=0)


@pytest.fixture(scope="module")
def dear():
    cfg = update.AgentConfig(method="dear", **SMALL)
    return cfg, _init(cfg, jax.random.key(0))


def test_critic_loss_against_the_target_critics_clipped_double_q_by_hand():
    """L_critic = MSE(Q1, y) + MSE(Q2, y) with y = r + discount * min(Q1', Q2'): Q' the target
    critic (moved away from the critic, which it equals at init) at the next latent and the
    policy's next action, its noise clipped at stddev_clip (std 1 against a clip of 0.3: the
    clip binds), clamped to (-1, 1). By hand with NumPy from the networks' outputs and the
    update's own draws (`learner_loss`'s key split: obs, next, far, target, TED)."""
    cfg = update.AgentConfig(method="drqv2", **SMALL)
    nets = update.make_networks(cfg)
    state = _init(cfg, jax.random.key(0))
    rng = np.random.default_rng(1)
    target_critic = jax.tree.map(
        lambda x: x + 0.1 * rng.standard_normal(x.shape).astype(np.float32), state.target_critic
    )
    reward, discount = np.float32([0.0, 0.5, 1.0, 2.0]), np.float32([0.99, 0.5, 0.0, 0.9801])
    batch = _batch(2).replace(reward=jnp.asarray(reward), discount=jnp.asarray(discount))
    learner = {k: v for k, v in state.params.items() if k != "actor"}
    actor, key, std = state.params["actor"], jax.random.key(3), 1.0
    loss = jax.jit(functools.partial(update.learner_loss, cfg=cfg))
    _, (metrics, _) = loss(learner, actor, target_critic, batch, key, update.HParams(), std)

    k_obs, k_next, _, k_target, _ = jax.random.split(key, 5)

    def latent(obs, k):
        crops = augment.Crops.sample(k, B, cfg.augment_pad, cfg.shift_impl)
        return nets.encoder.apply({"params": learner["encoder"]}, obs, crops)

    z, z_next = latent(batch.obs, k_obs), latent(batch.next_obs, k_next)
    mean = np.asarray(nets.actor.apply({"params": actor}, z_next))
    noise = np.clip(std * np.asarray(jax.random.normal(k_target, mean.shape)), -0.3, 0.3)
    assert np.abs(std * np.asarray(jax.random.normal(k_target, mean.shape))).max() > 0.3
    next_action = np.clip(mean + noise, -1 + 1e-6, 1 - 1e-6)
    tq1, tq2 = map(np.asarray, nets.critic.apply({"params": target_critic}, z_next, next_action))
    y = reward + discount * np.minimum(tq1, tq2)
    q1, q2 = map(np.asarray, nets.critic.apply({"params": learner["critic"]}, z, batch.action))
    np.testing.assert_allclose(metrics["target_q"], y.mean(), rtol=1e-5)
    want = np.mean((q1 - y) ** 2) + np.mean((q2 - y) ** 2)
    np.testing.assert_allclose(metrics["critic_loss"], want, rtol=1e-5)


def test_the_mask_target_is_cropped_as_the_observation(dear):
    """The mask decoder's target is the agent mask shifted as the observation was (the same
    crop), not as the next observation or unshifted: `mask_loss` of `learner_loss` against
    losses.mask_loss of the decoder's logits at z_A and the mask under the obs's crop. The
    decoder's weights (6 layers, ReLU, zero biases) are scaled by 5, its logits by 5^6, from
    ~1e-4 at init to ~1: the loss then depends on where the mask lies."""
    cfg, state = dear
    nets = update.make_networks(cfg)
    learner = {k: v for k, v in state.params.items() if k != "actor"}
    learner["mask_decoder"] = jax.tree.map(lambda x: 5.0 * x, learner["mask_decoder"])
    batch, key = _batch(5), jax.random.key(6)
    loss = jax.jit(functools.partial(update.learner_loss, cfg=cfg))
    _, (metrics, _) = loss(
        learner, state.params["actor"], state.target_critic, batch, key, update.HParams(), 0.5
    )
    k_obs, k_next = jax.random.split(key, 5)[:2]
    crops, next_crops = (
        augment.Crops.sample(k, B, cfg.augment_pad, cfg.shift_impl) for k in (k_obs, k_next)
    )
    z = nets.encoder.apply({"params": learner["encoder"]}, batch.obs, crops)
    logits = nets.mask_decoder.apply({"params": learner["mask_decoder"]}, losses.split_latent(z)[1])
    want = losses.mask_loss(logits, crops.apply(batch.mask))
    np.testing.assert_allclose(metrics["mask_loss"], want, rtol=1e-5)
    for other in (next_crops.apply(batch.mask), batch.mask):
        assert not np.isclose(losses.mask_loss(logits, other), want, rtol=1e-3)


def test_actor_loss_reaches_no_encoder_parameter(dear):
    cfg, state = dear
    batch = _batch(3)
    learner = {k: v for k, v in state.params.items() if k != "actor"}
    hp = update.HParams()

    def actor_loss_of_encoder(encoder_params, stop):
        ps = {**learner, "encoder": encoder_params}
        if stop:  # the latent the update hands to the actor step
            _, (_, z) = update.learner_loss(
                ps,
                state.params["actor"],
                state.target_critic,
                batch,
                jax.random.key(4),
                hp,
                jnp.float32(0.5),
                cfg=cfg,
            )
        else:  # what the actor step would see without DrQ-v2's detach
            z = update.make_networks(cfg).encoder.apply({"params": encoder_params}, batch.obs)
        return update.actor_loss(
            state.params["actor"], learner["critic"], z, jax.random.key(5), hp, 0.5, cfg=cfg
        )[0]

    grad = jax.jit(jax.grad(actor_loss_of_encoder), static_argnums=1)
    g_stop = grad(learner["encoder"], True)
    g_free = grad(learner["encoder"], False)
    assert all(np.all(np.asarray(x) == 0.0) for x in jax.tree.leaves(g_stop))
    assert sum(float(jnp.abs(x).sum()) for x in jax.tree.leaves(g_free)) > 0


def test_encoder_learns_from_critic_and_aux_losses(dear):
    """Each of the critic, mask and orthogonality losses moves the encoder's gradient: with
    alpha = beta = 0 it is the critic's alone (and the decoder's is 0); the mask loss
    (alpha > 0) and the orthogonality loss (beta > 0) each change it."""
    cfg, state = dear
    learner = {k: v for k, v in state.params.items() if k != "actor"}
    grad = jax.jit(jax.grad(update.learner_loss, has_aux=True), static_argnames="cfg")

    def grads(alpha, beta):
        g, (metrics, _) = grad(
            learner,
            state.params["actor"],
            state.target_critic,
            _batch(6),
            jax.random.key(7),
            update.HParams(alpha=alpha, beta=beta),
            jnp.float32(0.5),
            cfg=cfg,
        )
        return g, metrics

    def size(tree):
        return sum(float(jnp.abs(x).sum()) for x in jax.tree.leaves(tree))

    def gap(a, b):
        return size(jax.tree.map(lambda x, y: x - y, a, b))

    critic_only, _ = grads(0.0, 0.0)
    assert size(critic_only["encoder"]) > 0 and size(critic_only["critic"]) > 0
    assert size(critic_only["mask_decoder"]) == 0
    with_mask, _ = grads(0.25, 0.0)
    with_ortho, _ = grads(0.0, 100.0)
    dear_grads, metrics = grads(0.25, 100.0)
    assert size(with_mask["mask_decoder"]) > 0
    assert gap(with_mask["encoder"], critic_only["encoder"]) > 0
    assert gap(with_ortho["encoder"], critic_only["encoder"]) > 0
    assert gap(dear_grads["encoder"], with_mask["encoder"]) > 0
    expected = metrics["critic_loss"] + 0.25 * metrics["mask_loss"] + 100.0 * metrics["ortho_loss"]
    np.testing.assert_allclose(metrics["loss"], expected, rtol=1e-5)


def test_one_update_moves_params_and_target_is_ema(dear):
    cfg, state = dear
    hp = update.HParams(tau=0.25)
    new, metrics = _jitted_update(cfg)(state, _batch(8), jax.random.key(9), hp)
    for name in ("encoder", "actor", "critic", "mask_decoder"):
        moved = jax.tree.map(
            lambda a, b: bool(jnp.any(a != b)), state.params[name], new.params[name]
        )
        assert any(jax.tree.leaves(moved)), name
    ema = jax.tree.map(lambda t, c: 0.75 * t + 0.25 * c, state.target_critic, new.params["critic"])
    for a, b in zip(jax.tree.leaves(ema), jax.tree.leaves(new.target_critic)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    assert int(new.updates) == 1 and all(np.isfinite(float(v)) for v in metrics.values())


def test_acting_phases_and_schedule(dear):
    cfg, state = dear
    obs = jnp.asarray(np.random.default_rng(10).integers(0, 256, (8, 84, 84, 9), np.uint8))
    hp = update.HParams(explore_steps=16.0, std_steps=100.0, std_init=1.0, std_final=0.1)
    act = jax.jit(functools.partial(update.act, cfg), static_argnames="explore")
    mean, same = act(state, obs, jax.random.key(11), hp, explore=False)
    assert int(same.steps) == 0
    a1, s1 = act(state, obs, jax.random.key(12), hp, explore=True)
    assert int(s1.steps) == 8
    # Envs that restart this step ignore their actions: only the others count as steps.
    stepping = jnp.array([True, False, True, True, False, True, True, False])
    _, s5 = act(state, obs, jax.random.key(12), hp, explore=True, stepping=stepping)
    assert int(s5.steps) == 5
    # During the first explore_steps steps actions are the uniform draw of the key's second half,
    # whatever the policy; from then on the policy's (std 0 here: exactly its mean).
    still = update.HParams(explore_steps=16.0, std_steps=100.0, std_init=0.0, std_final=0.0)
    key = jax.random.key(14)
    uniform = jax.random.uniform(jax.random.split(key)[1], mean.shape, minval=-1.0, maxval=1.0)
    shifted = jax.tree.map(lambda x: x + 0.5, same.params["actor"])
    other = same.replace(params={**same.params, "actor": shifted})  # another policy
    for steps, expected in ((0, uniform), (15, uniform), (16, mean)):
        a, _ = act(same.replace(steps=jnp.int32(steps)), obs, key, still, explore=True)
        np.testing.assert_array_equal(a, expected)
        b, _ = act(other.replace(steps=jnp.int32(steps)), obs, key, still, explore=True)
        assert np.array_equal(a, b) == (steps < 16)  # the policy matters only after exploring
    assert not np.allclose(uniform, mean, atol=0.3)
    late = s1.replace(steps=jnp.int32(10_000))
    a2, _ = act(late, obs, jax.random.key(13), hp, explore=True)
    # After the decay, std = 0.1: actions stay near the mean.
    assert np.abs(np.asarray(a2 - mean)).max() < 0.6
    np.testing.assert_allclose(update.std_schedule(jnp.float32(50.0), hp), 0.55, rtol=1e-6)
    np.testing.assert_allclose(update.std_schedule(jnp.float32(500.0), hp), 0.1, rtol=1e-6)


def test_held_exploration_keeps_each_envs_draw_for_noise_hold_steps(dear):
    cfg, state = dear
    envs = 4
    obs = jnp.asarray(np.random.default_rng(15).integers(0, 256, (envs, 84, 84, 9), np.uint8))
    act = jax.jit(functools.partial(update.act, cfg), static_argnames="explore")
    hold = jax.random.key(16)
    for explore_steps in (0.0, 1e6):  # the policy's noise (constant std), then uniform actions
        hp = update.HParams(explore_steps=explore_steps, std_init=0.5, std_final=0.5)
        # noise_hold 1 (the default): the step's own key, with or without a hold key
        iid, _ = act(state, obs, jax.random.key(17), hp, explore=True)
        same, _ = act(state, obs, jax.random.key(17), hp, explore=True, hold_key=hold)
        np.testing.assert_array_equal(iid, same)
        # noise_hold 3: agent steps 0-2 of each env (the seed's counter 0, 4, 8) draw alike,
        # whatever their step keys; step 3 starts the next block
        held = hp.replace(noise_hold=3.0)
        out = [
            act(
                state.replace(steps=jnp.int32(envs * t)),
                obs,
                jax.random.key(20 + t),
                held,
                explore=True,
                hold_key=hold,
            )[0]
            for t in range(4)
        ]
        np.testing.assert_array_equal(out[0], out[1])
        np.testing.assert_array_equal(out[0], out[2])
        assert not np.allclose(out[2], out[3], atol=1e-3)
        assert not np.allclose(out[0][0], out[0][1], atol=1e-3)  # each env its own draw
        assert not np.allclose(out[0], iid, atol=1e-3)  # from the hold key, not the step's
        other, _ = act(
            state, obs, jax.random.key(20), held, explore=True, hold_key=jax.random.key(3)
        )
        assert not np.allclose(out[0], other, atol=1e-3)  # another seed's key, other draws


def test_lanes_hold_keys_follow_their_seeds():
    from configs.base import get_config
    from dear_jax.programs import hold_keys

    c = get_config()
    c.seeds = 2
    c.sweep.beta = "1,10"
    keys = np.asarray(hold_keys(c))  # lanes: beta 1 seeds 0, 1; beta 10 seeds 0, 1
    assert keys.shape[0] == 4 and keys.dtype == np.uint32
    seeds = [lane.seed for lane in lanes.lanes(c)]
    for i, j in itertools.combinations(range(4), 2):
        assert np.array_equal(keys[i], keys[j]) == (seeds[i] == seeds[j])
    c.seed = 1
    assert not np.array_equal(np.asarray(hold_keys(c))[0], keys[0])


def test_sample_action_clips_noise_and_passes_gradient_through_clamp():
    """Noise of std 10 clipped to +-0.3; means of +-1.5 end beyond the bounds whatever the draw,
    so they are clamped to +-(1 - 1e-6), and the gradient still reaches them (a plain clip would
    give 0 there)."""
    mean = jnp.array([0.0, 0.2, 1.5, -1.5])
    a = np.asarray(update.sample_action(mean, 10.0, jax.random.key(0), clip=0.3))
    assert np.all(np.abs(a[:2] - np.asarray(mean[:2])) <= 0.3 + 1e-6)
    np.testing.assert_array_equal(a[2:], np.float32([1 - 1e-6, -1 + 1e-6]))
    g = jax.grad(lambda m: update.sample_action(m, 10.0, jax.random.key(0), 0.3).sum())(mean)
    np.testing.assert_array_equal(g, [1.0, 1.0, 1.0, 1.0])


@pytest.mark.parametrize("method", update.METHODS)
def test_vmapped_seeds_every_method(method):
    cfg = update.AgentConfig(method=method, **SMALL)
    seeds = 2
    seed_keys = jax.random.split(jax.random.key(0), seeds)
    states = jax.jit(functools.partial(update.init_seeds, cfg))(seed_keys)
    enc = states.params["encoder"]["Dense_0"]["kernel"]
    assert not np.array_equal(enc[0], enc[1])  # different seeds, different parameters
    one = _init(cfg, seed_keys[1])  # seed i of the batch is the agent init(key i) makes
    for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(states)):
        np.testing.assert_allclose(a, b[1], rtol=1e-6, atol=1e-7)
    batches = _batches([1, 2], far=method == "ted")
    # Loss weights may differ across the vmapped seeds.
    hp = update.HParams(alpha=jnp.array([0.25, 1.0]), beta=jnp.array([100.0, 1.0])).for_seeds(seeds)
    step = jax.jit(jax.vmap(functools.partial(update.update, cfg=cfg)))
    keys = jax.random.split(jax.random.key(2), seeds)
    new, metrics = step(states, batches, keys, hp)
    for name, value in metrics.items():
        assert value.shape == (seeds,) and np.all(np.isfinite(np.asarray(value))), name
    # Seed 1 of the vmapped update is the update of seed 1 alone, with its own weights.
    pick = lambda tree: jax.tree.map(lambda x: x[1], tree)  # noqa: E731
    alone, alone_metrics = _jitted_update(cfg)(pick(states), pick(batches), keys[1], pick(hp))
    for a, b in zip(jax.tree.leaves((alone, alone_metrics)), jax.tree.leaves(pick((new, metrics)))):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
    if method == "dear":
        # The other seed axes: one traced update per seed ("loop"), or vmapped with the
        # convolutions unrolled over seeds ("hybrid"); the same numbers as vmap. (The Pallas
        # filter gradients and conv stacks are the same functions as the convolutions:
        # tests/test_networks.py and tests/test_wideconv.py.)
        for how in ("loop", "hybrid"):
            other = jax.jit(update.over_seeds(functools.partial(update.update, cfg=cfg), how))
            other_state, other_metrics = other(states, batches, keys, hp)
            for a, b in zip(
                jax.tree.leaves((new, metrics)), jax.tree.leaves((other_state, other_metrics))
            ):
                np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5, err_msg=how)
        np.testing.assert_allclose(
            metrics["loss"],
            metrics["critic_loss"]
            + hp.alpha * metrics["mask_loss"]
            + hp.beta * metrics["ortho_loss"],
            rtol=1e-5,
        )


def test_every_shift_impl_gives_the_same_update(dear):
    """agent.shift_impl changes how the random shift is computed, not the update: the same
    parameters, batch and key give the same learner loss, metrics and gradients (the shifted
    pixels are equal bit for bit, tests/test_augment.py; the programs around them fuse
    differently, so float sums may round differently: each gradient leaf within 1e-4 of its
    largest entry). Gradients, not parameters after an Adam step, which moves a parameter by
    about lr x the sign of its gradient and so turns a rounding near 0 into 2 lr."""
    cfg, state = dear
    learner = {k: v for k, v in state.params.items() if k != "actor"}
    grad = jax.jit(jax.grad(update.learner_loss, has_aux=True), static_argnames="cfg")
    key, hp = jax.random.key(8), update.HParams()
    for batch in (_batch(6), _batch(22)):
        results = {}
        for impl in ("pad_slice", "gather", "one_hot"):
            c = update.AgentConfig(method="dear", shift_impl=impl, **SMALL)
            g, (metrics, _) = grad(
                learner, state.params["actor"], state.target_critic, batch, key, hp,
                jnp.float32(0.5), cfg=c,
            )  # fmt: skip
            results[impl] = (g, metrics)
        want_g, want_m = results["pad_slice"]
        for impl in ("gather", "one_hot"):
            got_g, got_m = results[impl]
            for k in want_m:
                np.testing.assert_allclose(got_m[k], want_m[k], rtol=1e-5, err_msg=k)
            for a, b in zip(jax.tree.leaves(got_g), jax.tree.leaves(want_g)):
                scale = float(jnp.abs(b).max())
                np.testing.assert_allclose(a, b, rtol=0, atol=1e-4 * scale + 1e-12, err_msg=impl)
        assert float(want_m["critic_loss"]) > 0
    with pytest.raises(ValueError, match="unknown shift_impl 'roll'"):
        update.AgentConfig(action_dim=2, shift_impl="roll")


def test_ted_loss_over_a_split_batch_is_the_whole_batchs():
    """With a batch split in equal parts over a mapped axis (`devices_per_seed`), the parts'
    mean TED loss and accuracy are the whole batch's: the valid pairs are counted over all parts.
    The parts here hold 4 and 0 valid same-episode pairs, where the mean of each part's own mean
    differs. Every next latent is the same, so the other-sample negatives do not depend on the
    draw (which is made within each part)."""
    cfg = update.AgentConfig(method="ted", **SMALL)
    nets = update.make_networks(cfg)
    params = _init(cfg, jax.random.key(0)).params["ted"]
    rng = np.random.default_rng(0)
    z, z_far = (rng.normal(size=(8, 64)).astype(np.float32) for _ in range(2))
    z_next = np.tile(rng.normal(size=(1, 64)).astype(np.float32), (8, 1))
    valid = np.array([1, 1, 1, 1, 0, 0, 0, 0], np.float32)
    key = jax.random.key(1)

    def ted(z, z_next, z_far, valid, mean_over=None):
        return update.ted_classifier_loss(
            params, z, z_next, z_far, valid, key, nets=nets, mean_over=mean_over
        )

    whole_loss, whole = ted(z, z_next, z_far, valid)
    parts = [x.reshape(2, 4, *x.shape[1:]) for x in (z, z_next, z_far, valid)]
    split = jax.vmap(functools.partial(ted, mean_over="part"), axis_name="part")
    loss, metrics = split(*parts)
    np.testing.assert_allclose(loss.mean(), whole_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["ted_accuracy"].mean(), whole["ted_accuracy"], rtol=1e-5)
    own, _ = jax.vmap(ted)(*parts)  # each part normalised by its own count
    assert not np.isclose(own.mean(), whole_loss, rtol=1e-3)


def _ted_by_hand(ted_form: str, seed: int, key: jax.Array):
    """TED's classifier and 4 latents z, z_next, z_far for a loss computed by hand: (params,
    nets, latents, logits(a, b) in float64, the key's shuffle, and its cycle: sample perm[p]
    takes perm[p + 1]'s)."""
    cfg = update.AgentConfig(method="ted", ted_form=ted_form, **SMALL)
    nets = update.make_networks(cfg)
    params = _init(cfg, jax.random.key(0)).params["ted"]
    rng = np.random.default_rng(seed)
    latents = [rng.normal(size=(4, 64)).astype(np.float32) for _ in range(3)]
    perm = np.asarray(jax.random.permutation(key, 4))
    other = np.empty(4, int)
    other[perm] = np.roll(perm, -1)
    assert (other != np.arange(4)).all()

    def logits(a, b):
        return np.asarray(nets.ted.apply({"params": params}, a, b), np.float64)

    return params, nets, latents, logits, perm, other


def test_ted_reference_form_substitutes_another_samples_frame_for_a_missing_negative():
    """ted_form "reference_code": a sample without a same-episode frame pairs z_t with the frame
    drawn for another, the next in the shuffle's cycle, and every pair counts; the loss by hand
    from the classifier's logits (BCE = softplus(x) - x * label)."""
    key = jax.random.key(1)
    params, nets, (z, z_next, z_far), logits, perm, other = _ted_by_hand("reference_code", 3, key)
    valid = np.array([1, 0, 1, 0], np.float32)
    far = np.where(valid[:, None] > 0, z_far, z_far[other])
    x = np.concatenate([logits(z, z_next), logits(z, z_next[perm]), logits(z, far)])
    labels = np.concatenate([np.ones(4), np.zeros(8)])
    want = np.mean(np.logaddexp(0, x) - x * labels)
    got, _ = update.ted_classifier_loss(
        params, z, z_next, z_far, valid, key, nets=nets, substitute=True
    )
    np.testing.assert_allclose(got, want, rtol=1e-5)
    dropped, _ = update.ted_classifier_loss(params, z, z_next, z_far, valid, key, nets=nets)
    assert not np.isclose(dropped, want, rtol=1e-3)  # "strict" drops the two pairs instead


def test_ted_strict_form_pairs_z_t_with_another_samples_next_latent():
    """ted_form "strict": the other-sample negative is z_t+n of the next sample in the shuffle's
    cycle, never a sample's own, even where the shuffle leaves a sample in place (key 0 keeps
    samples 0 and 1); same-episode pairs without a frame are dropped. The loss by hand."""
    key = jax.random.key(0)
    params, nets, (z, z_next, z_far), logits, perm, other = _ted_by_hand("strict", 4, key)
    assert (perm == np.arange(4)).any()  # a plain shuffle would pair a sample with its own
    valid = np.array([1, 0, 1, 1], np.float32)
    x = np.concatenate([logits(z, z_next), logits(z, z_next[other]), logits(z, z_far)])
    labels = np.concatenate([np.ones(4), np.zeros(8)])
    weights = np.concatenate([np.ones(8), valid])
    want = np.sum(weights * (np.logaddexp(0, x) - x * labels)) / weights.sum()
    got, _ = update.ted_classifier_loss(params, z, z_next, z_far, valid, key, nets=nets)
    np.testing.assert_allclose(got, want, rtol=1e-5)


def test_ted_gradient_reaches_the_encoder_through_z_t_only():
    """TED's encoder gradient is J_enc(obs)^T dL/dz_t: the next and same-episode observations
    are encoded without gradient (TED's reference). Checked as the difference of the encoder
    gradient at two TED weights (the critic's part cancels), against that product computed by
    hand. Batch 1 and no augmentation make the sampled negatives and shifts deterministic."""
    cfg = update.AgentConfig(method="ted", augment_pad=0, **SMALL)
    nets = update.make_networks(cfg)
    state = _init(cfg, jax.random.key(0))
    batch = jax.tree.map(lambda x: x[:1], _batch(4, far=True))
    learner = {k: v for k, v in state.params.items() if k != "actor"}
    key = jax.random.key(5)

    # Jitted (the weight traced: one program for both): op by op, each operation of the loss
    # and its gradient compiles on its own.
    @jax.jit
    def encoder_grad(weight):
        hp = update.HParams(ted_weight=weight)
        grads, _ = jax.grad(update.learner_loss, has_aux=True)(
            learner, state.params["actor"], state.target_critic, batch, key, hp, 0.2, cfg=cfg
        )
        return grads["encoder"]

    got = jax.tree.map(jnp.subtract, encoder_grad(3.0), encoder_grad(1.0))

    def encode(enc, obs):
        return nets.encoder.apply({"params": enc}, obs)

    @jax.jit
    def by_hand(learner):
        z_next, z_far = (
            encode(learner["encoder"], batch.next_obs),
            encode(learner["encoder"], batch.far_obs),
        )
        k_ted = jax.random.split(key, 5)[4]  # learner_loss's key for TED's shuffle (no-op at B=1)
        dl_dz = jax.grad(
            lambda z: update.ted_classifier_loss(
                learner["ted"], z, z_next, z_far, batch.far_valid, k_ted, nets=nets
            )[0]
        )(encode(learner["encoder"], batch.obs))
        _, vjp = jax.vjp(lambda enc: encode(enc, batch.obs), learner["encoder"])
        return vjp(2.0 * dl_dz)[0]

    want = by_hand(learner)
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_allclose(g, w, rtol=2e-3, atol=1e-6)
    assert max(float(jnp.abs(w).max()) for w in jax.tree.leaves(want)) > 0
