"""Sweeps as lanes: settings crossed with seeds, each lane with its own loss weights."""

import dataclasses
import functools
import re

import jax
import numpy as np
import pytest
from test_update import SMALL, _batch

from configs import base
from dear_jax import experiment, lanes, losses, update
from dear_jax.config import check_override_keys


def sweep_config(seeds=2, method="dear", **sweep):
    c = base.get_config()
    c.seeds = seeds
    c.agent.method = method
    for key, values in sweep.items():
        c.sweep[key] = values
    return c


def test_sweepable_keys_are_the_updates_per_lane_numbers():
    assert lanes.SWEEPABLE == tuple(f.name for f in dataclasses.fields(update.HParams))
    assert set(base.get_config().sweep) == set(lanes.SWEEPABLE)


def test_lanes_cross_settings_with_seeds():
    c = sweep_config(seeds=2, beta="-1,0,100", alpha="0.25,0")
    runs = lanes.lanes(c)
    assert [r.name for r in runs[:4]] == [
        "alpha=0.25_beta=-1_seed_0",
        "alpha=0.25_beta=-1_seed_1",
        "alpha=0.25_beta=0_seed_0",
        "alpha=0.25_beta=0_seed_1",
    ]
    assert len(runs) == 12 and [r.index for r in runs] == list(range(12))
    assert [r.seed for r in runs] == [0, 1] * 6
    hp = experiment.hparams(c)
    np.testing.assert_array_equal(hp.beta, [-1, -1, 0, 0, 100, 100] * 2)
    np.testing.assert_array_equal(hp.alpha, [0.25] * 6 + [0.0] * 6)
    np.testing.assert_array_equal(
        hp.tau, np.float32([c.agent.tau] * 12)
    )  # not swept: the config's value
    one = lanes.lane_config(c, runs[3])
    assert (one.agent.beta, one.agent.alpha, one.seeds, one.lane.seed) == (0.0, 0.25, 1, 1)
    assert not any(one.sweep.values())
    # Without a sweep the lanes are the seeds, named as before.
    assert [r.name for r in lanes.lanes(sweep_config(seeds=3))] == ["seed_0", "seed_1", "seed_2"]


def test_bad_sweeps_are_refused_naming_the_key():
    c = sweep_config(gamma="1,2")
    with pytest.raises(ValueError, match=r"unknown sweep key 'gamma'.*: alpha, beta, recon_weight"):
        experiment.validate(c)
    with pytest.raises(KeyError, match=r"'sweep.gamma'.*Valid fields of sweep: alpha, beta"):
        check_override_keys(base.get_config(), ["--config.sweep.gamma=1,2"])
    with pytest.raises(ValueError, match=r"sweep.beta has no effect on agent.method='drqv2'"):
        experiment.validate(sweep_config(method="drqv2", beta="0,1"))
    with pytest.raises(ValueError, match=r"sweep.beta='1,x': give comma-separated numbers"):
        lanes.lanes(sweep_config(beta="1,x"))
    with pytest.raises(ValueError, match="repeats a value"):
        lanes.lanes(sweep_config(beta="1,1.0"))
    # Values named alike (6 significant digits) would write to one lane folder.
    with pytest.raises(ValueError, match=r"named alike \(beta=1\) would share a lane folder"):
        lanes.lanes(sweep_config(beta="1,1.0000001"))
    # A swept value is checked as the config's own field is: range, finiteness, whole numbers.
    for key, text, match in [
        ("noise_hold", "1,0.5", "noise_hold must be a whole number >= 1, got 0.5"),
        ("tau", "0.01,5", r"tau must be a finite number in \(0, 1\], got 5"),
        ("beta", "nan,1", "beta must be a finite number, got nan"),
        ("stddev_clip", "-1,1", "stddev_clip must be a finite number >= 0, got -1"),
        ("std_steps", "1.5,2", "std_steps must be a whole number >= 1, got 1.5"),
        ("explore_steps", "-100,0", "explore_steps must be a whole number >= 0, got -100"),
    ]:
        with pytest.raises(ValueError, match=rf"sweep.{key}='{re.escape(text)}': {match}"):
            lanes.lanes(sweep_config(**{key: text}))
    c = base.get_config()
    c.agent.noise_hold = 0
    with pytest.raises(ValueError, match="agent.noise_hold must be a whole number >= 1, got 0"):
        experiment.validate(c)
    np.testing.assert_array_equal(
        experiment.hparams(sweep_config(noise_hold="1,10")).noise_hold, [1, 1, 10, 10]
    )


def test_lanes_use_their_own_weights():
    """The trainer's per-lane numbers for a sweep of beta over {0, 100}, applied to the same
    parameters, batch and key: the lanes' losses differ by exactly 100 L_dis, and their encoder
    gradients by exactly 100 x the orthogonality loss's own gradient, computed here through the
    encoder by hand; so the beta = 0 lane gets none of it. No augmentation (pad 0) makes the
    encoded batch the raw one."""
    hp = experiment.hparams(sweep_config(seeds=1, beta="0,100"))
    cfg = update.AgentConfig(method="dear", augment_pad=0, **SMALL)
    nets = update.make_networks(cfg)
    # Jitted, as the gradients below: op by op, each operation compiles on its own.
    state = jax.jit(update.init, static_argnums=0)(cfg, jax.random.key(0))
    learner = {k: v for k, v in state.params.items() if k != "actor"}
    batch = _batch(1)
    loss = functools.partial(update.learner_loss, cfg=cfg)
    grad = jax.jit(jax.grad(loss, has_aux=True))
    lane = [
        grad(learner, state.params["actor"], state.target_critic, batch, jax.random.key(2), h, 0.2)
        for h in (jax.tree.map(lambda x, i=i: x[i], hp) for i in range(2))
    ]
    (g0, (m0, _)), (g1, (m1, _)) = lane
    assert m0["ortho_loss"] == m1["ortho_loss"] > 0
    np.testing.assert_allclose(m1["loss"] - m0["loss"], 100 * m0["ortho_loss"], rtol=1e-4)

    def encode(encoder):
        return nets.encoder.apply({"params": encoder}, batch.obs)

    def ortho(z):
        z_env, z_agent = losses.split_latent(z)
        return losses.orthogonality_loss(z_agent, z_env, cfg.ortho_form)

    @jax.jit
    def ortho_gradient(encoder):
        z, vjp = jax.vjp(encode, encoder)
        return vjp(jax.grad(ortho)(z))[0]

    g_dis = ortho_gradient(learner["encoder"])
    flat = lambda tree: np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)])  # noqa: E731
    diff = flat(g1["encoder"]) - flat(g0["encoder"])
    want = 100 * flat(g_dis)
    assert np.abs(want).max() > 0
    np.testing.assert_allclose(diff, want, rtol=1e-3, atol=1e-4 * np.abs(want).max())
