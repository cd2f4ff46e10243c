"""The PyTorch reference (benchmarks/torch_reference.py) is the architecture dear_jax implements.

Skipped where PyTorch is not installed (CI): PyTorch is not a dependency of the project.
"""

import functools

import jax
import numpy as np
import pytest

torch = pytest.importorskip(
    "torch", reason="PyTorch is not installed (optional: SETUP_EXTRAS=dev,torch ./setup.sh)"
)

from benchmarks import torch_reference as T  # noqa: E402
from dear_jax import networks, update  # noqa: E402

CPU = torch.device("cpu")


def _jax_counts(cfg) -> dict:
    shapes = jax.eval_shape(functools.partial(update.init_params, cfg), jax.random.key(0))
    return {k: sum(int(np.prod(x.shape)) for x in jax.tree.leaves(v)) for k, v in shapes.items()}


def _torch_counts(method: str, encoder: str, action_dim: int = 6) -> dict:
    """Parameter counts of the PyTorch modules, built without their (QR-heavy) init."""
    enc = T.Encoder(encoder)
    modules = {
        "encoder": enc,
        "actor": T.Actor(enc.out_dim, action_dim),
        "critic": T.Critic(enc.out_dim, action_dim),
    }
    if method == "dear":
        modules["mask_decoder"] = T.MaskDecoder()
    return {k: T.count_params(m) for k, m in modules.items()}


def test_parameter_counts_equal_dear_jax():
    expected = _jax_counts(update.AgentConfig(action_dim=6, method="dear"))
    assert expected == T.JAX_PARAM_COUNTS
    assert _torch_counts("dear", "pool") == expected
    plain = update.AgentConfig(action_dim=6, method="drqv2", encoder="plain")
    assert _torch_counts("drqv2", "plain") == _jax_counts(plain)


def test_encoder_and_mask_decoder_compute_the_flax_functions():
    """The same weights (moved to PyTorch's layouts) give the same latent and mask logits."""
    rng = np.random.default_rng(0)
    obs = rng.integers(0, 256, (2, 84, 84, 9), dtype=np.uint8)
    z_half = rng.normal(size=(2, 2048)).astype(np.float32)
    enc, dec = networks.PoolEncoder(), networks.PoolDecoder(3)
    fill = lambda tree: jax.tree.map(  # noqa: E731
        lambda s: (0.05 * rng.normal(size=s.shape)).astype(np.float32), tree
    )
    pe = fill(jax.eval_shape(enc.init, jax.random.key(0), obs))
    pd = fill(jax.eval_shape(dec.init, jax.random.key(0), z_half))
    z_flax = np.asarray(jax.jit(enc.apply)(pe, obs))
    logits_flax = np.asarray(jax.jit(dec.apply)(pd, z_half))

    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    encoder, decoder = T.Encoder("pool"), T.MaskDecoder()
    with torch.no_grad():
        convs = [m for m in encoder.convs if isinstance(m, torch.nn.Conv2d)]
        for i, conv in enumerate(convs):
            p = pe["params"]["ConvTrunk_0"][f"Conv_{i}"]
            conv.weight.copy_(t(p["kernel"].transpose(3, 2, 0, 1)))  # HWIO -> OIHW
            conv.bias.copy_(t(p["bias"]))
        k = pe["params"]["Dense_0"]["kernel"]  # [(h, w, c), out] -> [out, (c, h, w)]
        encoder.fc.weight.copy_(t(k.reshape(8, 8, 32, -1).transpose(3, 2, 0, 1).reshape(-1, 2048)))
        encoder.fc.bias.copy_(t(pe["params"]["Dense_0"]["bias"]))
        z_torch = encoder(t(obs.transpose(0, 3, 1, 2))).numpy()

        k = pd["params"]["Dense_0"]["kernel"]  # [in, (h, w, c)] -> [(c, h, w), in]
        decoder.fc.weight.copy_(t(k.reshape(-1, 8, 8, 16).transpose(3, 1, 2, 0).reshape(1024, -1)))
        decoder.fc.bias.copy_(
            t(pd["params"]["Dense_0"]["bias"].reshape(8, 8, 16).transpose(2, 0, 1).ravel())
        )
        deconvs = [m for m in decoder.deconvs if isinstance(m, torch.nn.ConvTranspose2d)]
        for i, deconv in enumerate(deconvs):
            p = pd["params"][f"ConvTranspose_{i}"]
            # Our [kh, kw, in, out] kernel is PyTorch's [in, out, kh, kw] weight transposed and
            # flipped in space (PyTorch's transposed conv is the gradient of a conv: it flips).
            deconv.weight.copy_(t(p["kernel"].transpose(2, 3, 0, 1)[:, :, ::-1, ::-1]))
            deconv.bias.copy_(t(p["bias"]))
        logits_torch = decoder(t(z_half)).numpy().transpose(0, 2, 3, 1)
    np.testing.assert_allclose(z_torch, z_flax, rtol=2e-4, atol=2e-4)
    np.testing.assert_allclose(logits_torch, logits_flax, rtol=2e-4, atol=2e-4)


def test_gather_shift_equals_grid_sample_shift():
    x = torch.randint(0, 256, (5, 4, 84, 84), dtype=torch.uint8)
    shifts = torch.tensor([[0, 0], [8, 8], [0, 8], [3, 5], [8, 1]])
    gathered = T.shift_gather(x, shifts)
    sampled = T.shift_grid_sample(x.float(), shifts)
    assert gathered.dtype == torch.uint8
    torch.testing.assert_close(sampled, gathered.float(), atol=1e-2, rtol=0)
    # Offset 4 is the identity; offset 0 repeats the first row and column.
    assert torch.equal(T.shift_gather(x, torch.full((5, 2), 4)), x)
    assert torch.equal(gathered[0, :, :5, 0], x[0, :, 0:1, 0].expand(4, 5))


def test_one_update_on_cpu():
    torch.set_num_threads(1)
    agent = T.Agent("dear", 6, CPU, T.Variant.parse("eager"), aug="gather")
    counts = agent.param_counts()
    assert counts.pop("total") == sum(T.JAX_PARAM_COUNTS.values())
    assert counts == T.JAX_PARAM_COUNTS
    batch = T.random_batch(2, 6, CPU, with_mask=True)
    before = [p.clone() for p in agent.critic_target.parameters()]
    metrics = agent.update(batch, torch.tensor(0.5))
    assert set(metrics) == {"critic_loss", "mask_loss", "ortho_loss", "actor_loss"}
    assert all(np.isfinite(float(v)) for v in metrics.values())
    online = list(agent.critic.parameters())
    # The target starts as a copy of the critic, which the update moved.
    assert any(not torch.equal(cur, old) for old, cur in zip(before, online))
    for old, new, cur in zip(before, agent.critic_target.parameters(), online):
        # target = (1 - tau) old + tau online
        torch.testing.assert_close(new, torch.lerp(old, cur, T.TAU))


def test_replay_stacks_and_nstep_stay_in_their_episode():
    replay = T.Replay(16, 1, with_mask=True, nstep=2, gamma=0.5)
    frame = lambda v: np.full((3, 84, 84), v, np.uint8)  # noqa: E731
    mask = lambda v: np.full((84, 84), v, np.uint8)  # noqa: E731
    for episode in (0, 100):
        replay.start_episode(frame(episode), mask(episode))
        for t in range(1, 4):  # frames episode+1 .. episode+3; rewards 1, 2, 3
            replay.add(np.array([t], np.float32), float(t), frame(episode + t), mask(episode + t))
    # Valid starts: t = 0, 1 of each 4-frame episode (t + 2 must be in the episode).
    assert sorted(replay.valid[: replay.num_valid]) == [0, 1, 4, 5]
    n = 64
    out = {
        "obs": np.zeros((n, 9, 84, 84), np.uint8),
        "next_obs": np.zeros((n, 9, 84, 84), np.uint8),
        "mask": np.zeros((n, 3, 84, 84), np.uint8),
        "action": np.zeros((n, 1), np.float32),
        "reward": np.zeros(n, np.float32),
        "discount": np.zeros(n, np.float32),
    }
    replay.sample_into(np.random.default_rng(0), out)
    for i in range(n):
        last = int(out["obs"][i, 6, 0, 0])
        episode, t = (0, last) if last < 100 else (100, last - 100)
        expect = [episode + max(t - 2, 0), episode + max(t - 1, 0), episode + t]
        assert list(out["obs"][i, ::3, 0, 0]) == expect
        assert list(out["mask"][i, :, 0, 0]) == expect
        assert list(out["next_obs"][i, ::3, 0, 0]) == [
            episode + t,
            episode + t + 1,
            episode + t + 2,
        ]
        assert out["action"][i, 0] == t + 1
        assert out["reward"][i] == pytest.approx((t + 1) + 0.5 * (t + 2))
    assert np.all(out["discount"] == 0.25)
