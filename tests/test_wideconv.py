"""dear_jax.wideconv: stride-1 conv stacks as Pallas kernels (here in Pallas' interpreter)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dear_jax import networks, update, wideconv


def _lax_stack(x, layers, pad):
    for k, b in layers:
        x = jnp.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
        y = jax.lax.conv_general_dilated(
            x, k, (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"), precision="highest"
        )
        x = jax.nn.relu(y + b)
    return x


def _stack_inputs(key, size, channels, seeds=None):
    keys = jax.random.split(key, 2 * len(channels) + 1)
    lead = () if seeds is None else (seeds,)
    x = jax.random.normal(keys[0], (*lead, 2, size, size, channels[0]))
    layers = tuple(
        (
            jax.random.normal(keys[1 + 2 * i], (*lead, 3, 3, c, f)) * 0.2,
            jax.random.normal(keys[2 + 2 * i], (*lead, f)) * 0.1,
        )
        for i, (c, f) in enumerate(zip(channels, channels[1:]))
    )
    return x, layers


@pytest.mark.parametrize("width, block", [(4, 64), (1, 16)])
@pytest.mark.parametrize("pad, size", [(0, 11), (2, 5)])
def test_conv_stack_is_relu_convolutions_in_values_and_gradients(
    monkeypatch, width, block, pad, size
):
    """Encoder-like (VALID, pad 0) and transposed-like (pad 2) stacks, with 4-pixel windows and
    single taps: the values and every gradient (input, kernels, biases) of lax's convolutions."""
    monkeypatch.setattr(wideconv, "WIDTH", width)
    monkeypatch.setattr(wideconv, "BLOCK", block)
    x, layers = _stack_inputs(jax.random.key(0), size, (16, 32, 16))
    assert wideconv.supported(x.shape, layers, pad)
    got = wideconv.conv_stack(x, layers, pad)
    want = _lax_stack(x, layers, pad)
    assert got.shape == (2, size + 2 * (2 * pad - 2), size + 2 * (2 * pad - 2), 16)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)

    def loss(stack):
        return lambda x, ws: jnp.sum(jnp.sin(stack(x, ws, pad)))

    got = jax.grad(loss(wideconv.conv_stack), (0, 1))(x, layers)
    want = jax.grad(loss(_lax_stack), (0, 1))(x, layers)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4)
    # The ReLU gradient is applied: a stack whose pre-activations are all negative passes none.
    dead = tuple((k, b - 100.0) for k, b in layers)
    grads = jax.grad(loss(wideconv.conv_stack), (0, 1))(x, dead)
    assert all(float(jnp.abs(g).max()) == 0.0 for g in jax.tree.leaves(grads))


def test_conv_stack_under_vmap_is_each_seed_on_its_own():
    """Vmapped over seeds (each with its own weights), bf16 activations: every seed's values and
    gradients equal the same stack run for that seed alone."""
    x, layers = _stack_inputs(jax.random.key(1), 7, (16, 16), seeds=2)
    x = x.astype(jnp.bfloat16)

    def f(x, ws):
        return jnp.sum(wideconv.conv_stack(x, ws, 0).astype(jnp.float32) ** 2)

    both = jax.vmap(jax.value_and_grad(f, (0, 1)))(x, layers)
    for s in range(2):
        alone = jax.value_and_grad(f, (0, 1))(x[s], jax.tree.map(lambda a, s=s: a[s], layers))
        for a, b in zip(jax.tree.leaves(both), jax.tree.leaves(alone), strict=True):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(np.asarray(a[s], np.float32), np.asarray(b, np.float32))


def test_supported_shapes():
    k = lambda c, f: (jnp.zeros((3, 3, c, f)), jnp.zeros(f))  # noqa: E731
    assert wideconv.supported((2, 41, 41, 32), (k(32, 32),) * 3, 0)
    assert wideconv.supported((2, 35, 35, 16), (k(16, 32), k(32, 32), k(32, 32)), 2)
    assert not wideconv.supported((2, 41, 41, 12), (k(12, 32),), 0)  # 12: not a power of 2
    assert not wideconv.supported((2, 41, 40, 32), (k(32, 32),), 0)  # not square
    assert not wideconv.supported((2, 41, 41, 32), (k(32, 32),), 1)  # only pad 0 or 2
    assert not wideconv.supported((2, 41, 41, 32), (k(16, 32),), 0)  # kernel's channels differ
    assert not wideconv.supported((2, 5, 5, 32), (k(32, 32),) * 3, 0)  # nothing left: 5 -> -1


@pytest.mark.parametrize("width", [1, 4])
def test_stacks_lower_for_cuda_as_one_triton_kernel_per_layer_and_pass(monkeypatch, width):
    """Compiled (not interpreted) on any machine: forward, input gradient and filter gradient
    of each layer are one Triton kernel each, for all vmapped seeds."""
    monkeypatch.setattr(wideconv, "INTERPRET", False)
    monkeypatch.setattr(wideconv, "WIDTH", width)
    for pad, size, channels in [(0, 41, (32, 32, 32, 32)), (2, 35, (16, 32, 32, 32))]:
        x = jax.ShapeDtypeStruct((2, 8, size, size, channels[0]), jnp.bfloat16)
        layers = tuple(
            (
                jax.ShapeDtypeStruct((2, 3, 3, c, f), jnp.float32),
                jax.ShapeDtypeStruct((2, f), jnp.float32),
            )
            for c, f in zip(channels, channels[1:])
        )

        def loss(x, ws, pad=pad):
            return jnp.sum(wideconv.conv_stack(x, ws, pad).astype(jnp.float32))

        fn = jax.vmap(jax.value_and_grad(loss, (0, 1)))
        text = jax.jit(fn).trace(x, layers).lower(lowering_platforms=("cuda",)).as_text()
        assert text.count("xla.gpu.triton") == 9


def test_networks_with_pallas_stacks_are_the_same_function():
    """With conv_settings(stack="pallas") the pool encoder and decoder keep their parameters
    (names, shapes, initial values) and give the same values and gradients."""
    enc, dec = networks.PoolEncoder(64), networks.PoolDecoder(3)
    obs = jax.random.randint(jax.random.key(1), (1, 84, 84, 9), 0, 256).astype(jnp.uint8)
    z = jax.random.normal(jax.random.key(2), (1, 32))
    params = enc.init(jax.random.key(0), obs), dec.init(jax.random.key(0), z)

    def loss(p):
        latent = enc.apply(p[0], obs)
        return jnp.sum(latent**2) + jnp.sum(jnp.tanh(dec.apply(p[1], latent[:, :32])))

    want = jax.value_and_grad(loss)(params)
    with networks.conv_settings(stack="pallas"):
        same = enc.init(jax.random.key(0), obs), dec.init(jax.random.key(0), z)
        got = jax.value_and_grad(loss)(params)
    for a, b in zip(jax.tree.leaves(same), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


def test_unknown_stack_is_refused():
    with pytest.raises(ValueError, match="unknown conv stack 'cutlass'"):
        with networks.conv_settings(stack="cutlass"):
            pass
    with pytest.raises(ValueError, match="unknown conv_stack 'cutlass'.*'xla', 'pallas'"):
        update.AgentConfig(action_dim=6, conv_stack="cutlass")


def test_sweep_grid_and_pick_write_the_fastest_settings(tmp_path):
    """benchmarks.wideconv: a grid is the product of its settings, an unknown name is refused
    with the valid ones, and --pick writes the fastest variant's settings (both stacks' times of
    one pass, summed) into a module's defaults."""
    from benchmarks import wideconv as sweep

    assert sweep.parse_grid(["WIDTH=4,1", "BLOCK=64"]) == [
        {"WIDTH": 4, "BLOCK": 64},
        {"WIDTH": 1, "BLOCK": 64},
    ]
    with pytest.raises(SystemExit, match="NAME one of .*'BLOCK'"):
        sweep.parse_grid(["BLOKC=64"])
    module = tmp_path / "settings.py"
    module.write_text("BLOCK = 64  # rows\nNUM_WARPS = 4\nWIDTH = 4\n")
    rows = [
        dict(variant=v, settings=st, pass_=p, stack=s, ms_per_call=ms)
        for v, st, p, s, ms in [
            ("pallas_current", {}, "forward", "encoder", 2.0),
            ("pallas_current", {}, "forward", "decoder", 2.0),
            ("pallas_a", {"BLOCK": 128, "NUM_WARPS": 2}, "forward", "encoder", 1.5),
            ("pallas_a", {"BLOCK": 128, "NUM_WARPS": 2}, "forward", "decoder", 2.0),
            ("pallas_a", {"BLOCK": 128, "NUM_WARPS": 2}, "forward_backward", "encoder", 9.0),
            ("xla_loop", {}, "forward", "encoder", 0.1),
        ]
    ]
    results = tmp_path / "sweep.json"
    results.write_text(json.dumps(dict(rows=rows)))
    assert sweep.pick(str(results), "forward", module) == {"BLOCK": 128, "NUM_WARPS": 2}
    assert module.read_text() == "BLOCK = 128\nNUM_WARPS = 2\nWIDTH = 4\n"
    assert sweep.pick(str(results), "forward_backward", module) == {"BLOCK": 128, "NUM_WARPS": 2}
