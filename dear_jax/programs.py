"""The loop's jitted programs (act, learn, add, the evaluation's policy step), each over all
lanes at once; with a mesh, act, learn and add run each device's block of lanes on that device
(`jax.shard_map`; lanes are independent, so the only collective is the gradients' mean over a
lane's devices where its batch is split, `config.devices_per_seed`).
"""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P
from ml_collections import ConfigDict

from dear_jax import devices, lanes, losses, replay, update
from dear_jax.experiment import hparams, updates_per_call, xla_options


@dataclasses.dataclass(frozen=True)
class Programs:
    """The jitted functions of the loop, each over all seeds at once."""

    # (agent, obs [S,E,...], key, stepping [S,E], hold_keys(config) or None) -> (actions
    # [S,E,A], agent)
    act: callable
    # (agent, replay, key) -> (agent, metrics [S]): one update per seed; with
    # updates_per_call(config) K > 1, keys [K] -> K updates, their metrics summed
    learn: callable
    add: callable  # (replay, ts, action) -> replay
    # (params, obs) -> (actions, cos(z_A, z_E) of each env [S,E], predicted mask of env 0
    # [S,H,W])
    evaluate_step: callable
    # The same in float32, for the evaluation process on the host's CPU (eval_device="cpu",
    # dear_jax/evaluator.py): XLA:CPU runs bfloat16 convolutions at half float32's speed.
    evaluate_step_host: callable
    # (returns [S,E], ts) -> (returns, per seed the returns of the episodes ts ended, summed [S])
    accumulate: callable
    add_metrics: callable  # (metrics, metrics) -> elementwise sum


_PROGRAMS: dict = {}


def accumulate(returns, ts):
    """The returns of the episodes under way [S,E] after timestep `ts`, and per seed the sum of
    those of the episodes `ts` ends [S]."""
    returns = jnp.where(ts.first, 0.0, returns) + ts.reward
    return returns, jnp.where(ts.last, returns, 0.0).sum(-1)


def cached_programs(
    acfg: update.AgentConfig, config: ConfigDict, mesh: Mesh | None = None
) -> Programs:
    """build_programs, reused by later runs of this process with the same agent and seeds (tests,
    resumes in one process): their jitted functions are then compiled once per mesh."""
    settings = {k: config[k].to_dict() for k in ("agent", "sweep")}
    settings["replay.sampling"] = config.replay.sampling  # the learn program's sampler
    settings["updates_per_call"] = updates_per_call(config)  # "auto" resolved
    experiment = (acfg, config.seeds, json.dumps(settings, sort_keys=True))
    if (experiment, mesh) not in _PROGRAMS:
        hp = hparams(config)
        for key in [k for k in _PROGRAMS if k[0] != experiment]:
            del _PROGRAMS[key]  # a process runs one experiment at a time
        _PROGRAMS[experiment, mesh] = build_programs(acfg, hp, config, mesh)
    return _PROGRAMS[experiment, mesh]


# fold_in(key(config.seed), HOLD_STREAM): the root of the lanes' held-exploration keys.
HOLD_STREAM = 3_000_017


def hold_keys(config: ConfigDict) -> jax.Array:
    """Each lane's key for held exploration draws (`update.act`, agent.noise_hold), as key data
    [lanes, ...] uint32: from its seed alone, so the same on every process and after a resume
    (lanes of one seed share it, as they share their initial parameters)."""
    root = jax.random.fold_in(jax.random.key(config.seed), HOLD_STREAM)
    seeds = jnp.array([lane.seed for lane in lanes.lanes(config)])
    return jax.random.key_data(jax.vmap(lambda s: jax.random.fold_in(root, s))(seeds))


def build_programs(
    acfg: update.AgentConfig, hp: update.HParams, config: ConfigDict, mesh: Mesh | None = None
) -> Programs:
    """The loop's programs; with a `mesh`, act, learn and add run each device's block of seeds
    on that device. Per-seed keys are split before the split over devices, so a seed draws the
    same numbers on any number of devices (but for its batches where `devices_per_seed` > 1:
    each of its devices folds its index into the keys of its share)."""
    a = config.agent
    num_seeds = lanes.num_lanes(config)
    nets = update.make_networks(acfg)
    split = devices.batch_split(mesh)  # devices per lane, each drawing 1 / split of its batch

    def per_device(fn):
        """`fn` of a block of seeds ([S / N, ...] arguments), run where the block lives."""
        if mesh is None:
            return fn
        # check_vma=False: the bodies hold no collectives across "seeds" (each device runs its
        # own seeds). Over "batch" (a 2-D mesh) a lane's devices compute the same outputs: the
        # same inputs and programs, the gradients averaged over them (unchecked: an op that is
        # not deterministic on a GPU could let the copies of acting and replay differ). With the
        # check on, each pallas_call (wideconv, wgrad) would have to state its outputs' varying
        # axes in its out_shape, a jax-version-specific annotation kernels meant for one device
        # do not carry; without it, tracing fails.
        return jax.shard_map(
            fn, mesh=mesh, in_specs=P("seeds"), out_specs=P("seeds"), check_vma=False
        )

    # Acting, updating and evaluating run their seeds as agent.seed_axis says (sampling is always
    # vmapped: integer work, gathers and element-wise sums, the same for any number of seeds).
    # With "loop", a seed's computation is the same however many seeds share its device, so a
    # split run is the same bit for bit; a vmapped convolution of S seeds is one grouped
    # convolution whose rounding depends on S.
    def over_seeds(fn):
        return per_device(update.over_seeds(fn, a.seed_axis))

    def act(agent, obs, key, stepping, hold=None):
        keys = jax.random.split(key, num_seeds)

        def per_seed(agent, obs, key, hp, stepping, hold):
            hold_key = None if hold is None else jax.random.wrap_key_data(hold)
            return update.act(
                acfg, agent, obs, key, hp, explore=True, stepping=stepping, hold_key=hold_key
            )

        return over_seeds(per_seed)(agent, obs, keys, hp, stepping, hold)

    def sample_one(buffer, key):
        return replay.sample(
            buffer,
            key,
            a.batch_size // split,
            nstep=a.nstep,
            gamma=a.discount,
            frame_stack=acfg.frame_stack,
            same_episode=acfg.method == "ted",
            skip_positives=acfg.ted_form == "strict",
            by_episode=config.replay.sampling == "episode",
        )

    def update_one(agent, batch, key, hp_seed):
        axis = devices.BATCH if split > 1 else None
        return update.update(agent, batch, key, hp_seed, cfg=acfg, mean_over=axis)

    # One update per seed per call; the loop calls it E / update_every_steps times (dispatch is
    # asynchronous). A lax.scan over the updates made tests/test_run.py's tiny runs ~3x slower
    # on CPU (its fixture: 298 s with the scan, 97 s without; pytest --durations). On an H100 a
    # step's 8 updates of one DEAR seed took 32.1 ms as one program (the scan unrolled) against
    # 31.9 ms as 8 calls: the GPU, not the launches, sets their pace (commit 4bc20e4,
    # benchmarks/results/kernels/train_paper_dear_1seed_{calls,unrolled}_h100.json).
    # Batches are drawn for all seeds at once (vmapped gathers from the [S, T, E, ...] replay);
    # only the updates follow agent.seed_axis. Looping the sampling too, which slices each
    # seed's replay out of the buffer first, made DEAR's learn program on an H100 take 395
    # instead of 295 ms per 5 x 16 iteration (benchmarks/RESULTS.md, "End to end").
    def learn_block(agent, buffer, keys, hp):
        if split > 1:  # each of a lane's devices draws (and crops) its own part of the batch
            keys = jax.vmap(jax.random.fold_in, (0, None))(keys, jax.lax.axis_index(devices.BATCH))
        k_sample, k_update = jnp.moveaxis(jax.vmap(jax.random.split)(keys), 1, 0)
        batches = jax.vmap(sample_one)(buffer, k_sample)
        return update.over_seeds(update_one, a.seed_axis)(agent, batches, k_update, hp)

    def learn(agent, buffer, key):
        keys = jax.random.split(key, num_seeds)
        return per_device(learn_block)(agent, buffer, keys, hp)

    def learn_calls(agent, buffer, keys):
        """updates_per_call(config) updates in one program, one per key of keys [K] (a scan of
        `learn`); their metrics summed."""
        agent, metrics = jax.lax.scan(lambda ag, k: learn(ag, buffer, k), agent, keys)
        return agent, jax.tree.map(lambda m: m.sum(0), metrics)

    def add(buffer, ts, action):
        return per_device(jax.vmap(replay.add))(
            buffer, ts.frame, ts.mask, action, ts.reward, ts.discount, ts.first
        )

    def evaluate_step(nets):
        def one(params, obs):
            z = nets.encoder.apply({"params": params["encoder"]}, obs)
            action = nets.actor.apply({"params": params["actor"]}, z)
            z_env, z_agent = losses.split_latent(z)
            cos = losses.cosine_similarity(z_agent, z_env).astype(jnp.float32)  # [E]
            if nets.mask_decoder is None:
                pred = jnp.zeros(obs.shape[1:3])
            else:  # newest frame's channel of env 0
                logits = nets.mask_decoder.apply({"params": params["mask_decoder"]}, z_agent[:1])
                pred = jax.nn.sigmoid(logits[0, ..., -1])
            return action, cos, pred

        return one

    nets_f32 = update.make_networks(dataclasses.replace(acfg, compute_dtype="float32"))

    return Programs(
        act=jax.jit(act, donate_argnums=0),
        learn=jax.jit(
            learn if updates_per_call(config) == 1 else learn_calls,
            donate_argnums=0,
            compiler_options=xla_options(a.xla_options),
        ),
        add=jax.jit(add, donate_argnums=0),
        evaluate_step=jax.jit(over_seeds(evaluate_step(nets))),
        evaluate_step_host=jax.jit(update.over_seeds(evaluate_step(nets_f32), a.seed_axis)),
        accumulate=jax.jit(accumulate),
        add_metrics=jax.jit(lambda a, b: jax.tree.map(jnp.add, a, b)),
    )
