"""Architecture: parameter counts of the reference, output shapes, DrQ-v2 initialisation."""

import functools
import re

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dear_jax import networks
from dear_jax.report import param_counts
from dear_jax.update import AgentConfig, init_params


# Inputs are drawn with NumPy: jax.random compiles a program per shape (seconds each).
def _normal(seed, shape):
    return jnp.asarray(np.random.default_rng(seed).normal(size=shape), jnp.float32)


def _pixels(seed, shape):
    return jnp.asarray(np.random.default_rng(seed).integers(0, 256, shape, np.uint8))


REFERENCE_COUNTS = {  # per module (docs/method.md, Architecture), walker |A| = 6
    "encoder": 8_423_072,
    "actor": 1_312_924,
    "critic": 2_422_936,
    "mask_decoder": 2_126_291,
    "recon_decoder": 2_128_025,
    "ted": 20_481,
}


@pytest.mark.parametrize("method", ["drqv2", "dear", "sear", "ted"])
def test_parameter_counts_equal_reference(method):
    counts = param_counts(AgentConfig(action_dim=6, method=method))
    expected_modules = {
        "drqv2": {"encoder", "actor", "critic"},
        "dear": {"encoder", "actor", "critic", "mask_decoder"},
        "sear": {"encoder", "actor", "critic", "mask_decoder", "recon_decoder"},
        "ted": {"encoder", "actor", "critic", "ted"},
    }[method]
    assert set(counts) == expected_modules
    for name, n in counts.items():
        assert n == REFERENCE_COUNTS[name], name


def test_plain_encoder_is_flattened_convs():
    counts = param_counts(AgentConfig(action_dim=6, method="drqv2", encoder="plain"))
    assert counts["encoder"] == 9 * 9 * 32 + 32 + 3 * (9 * 32 * 32 + 32)
    assert (
        counts["actor"]
        == 39200 * 50 + 50 + 100 + 50 * 1024 + 1024 + 1024 * 1024 + 1024 + 1024 * 6 + 6
    )


def _out_shape(module, *args):
    """Output shape without computing anything (init and apply traced abstractly)."""
    params = jax.eval_shape(module.init, jax.random.key(0), *args)
    return jax.eval_shape(module.apply, params, *args)


def test_shapes():
    obs = jnp.zeros((2, 84, 84, 9), jnp.uint8)
    z, half, a = jnp.zeros((2, 4096)), jnp.zeros((2, 2048)), jnp.zeros((2, 6))
    assert _out_shape(networks.PoolEncoder(), obs).shape == (2, 4096)
    assert _out_shape(networks.PlainEncoder(), obs).shape == (2, 39200)
    assert _out_shape(networks.PoolDecoder(3), half).shape == (2, 84, 84, 3)
    assert _out_shape(networks.PoolDecoder(9), half).shape == (2, 84, 84, 9)
    assert _out_shape(networks.Actor(6), z).shape == (2, 6)
    q1, q2 = _out_shape(networks.Critic(), z, a)
    assert q1.shape == q2.shape == (2,)
    assert _out_shape(networks.TEDClassifier(), z, z).shape == (2,)


@pytest.mark.parametrize("form", ["strict", "reference_code"])
def test_ted_classifier_values_and_initialisation(form):
    """logit = sum_F(|W0 z1 + W1 z2 + b| - (Wb z1 + bb)^2) + c, by hand from its parameters;
    "strict" draws W0 and W1 apart and starts c at 0, "reference_code" (TED's code) draws them
    as one orthogonal 2 x F matrix and c as +-1."""
    f = 16
    z1, z2 = _normal(0, (3, f)), _normal(1, (3, f))
    module = networks.TEDClassifier(form)
    params = module.init(jax.random.key(2), z1, z2)["params"]
    rows = {k: np.ravel(v) for k, v in params.items() if k not in ("w01", "c")}
    w0, w1 = params["w01"] if form == "reference_code" else (rows["w0"], rows["w1"])
    c = float(np.ravel(params["c"])[0])
    for w in (w0, w1, rows["b"], rows["wb"], rows["bb"]):  # orthogonal [1, F]: unit rows
        np.testing.assert_allclose(np.linalg.norm(w), 1.0, rtol=1e-5)
    if form == "reference_code":
        np.testing.assert_allclose(np.dot(w0, w1), 0.0, atol=1e-6)
        assert abs(c) == pytest.approx(1.0)
    else:
        assert abs(np.dot(w0, w1)) > 1e-3 and c == 0.0  # drawn apart: not orthogonal
    z1, z2 = np.asarray(z1), np.asarray(z2)
    want = (np.abs(w0 * z1 + w1 * z2 + rows["b"]) - (rows["wb"] * z1 + rows["bb"]) ** 2).sum(-1)
    got = module.apply({"params": params}, z1, z2)
    np.testing.assert_allclose(got, want + c, rtol=1e-5, atol=1e-5)


def test_decoder_and_actor_values():
    z = _normal(0, (2, 32))
    actor = networks.Actor(6, hidden_dim=16)
    mean = actor.apply(jax.jit(actor.init)(jax.random.key(1), z), z)
    assert np.all(np.abs(np.asarray(mean)) < 1.0)
    dec = networks.PoolDecoder(3)
    params = jax.jit(dec.init)(jax.random.key(2), z)
    out = dec.apply(params, z)
    assert out.shape == (2, 84, 84, 3) and np.all(np.isfinite(np.asarray(out)))
    phases = dec.apply(params, z, phases=True)
    assert phases.shape == (2, 42, 42, 12)
    np.testing.assert_array_equal(phases, networks.decoder_phases(out))
    # pixel (2i + ry, 2j + rx), channel c is channel (ry, rx, c) of pixel (i, j)
    np.testing.assert_array_equal(phases[1, 5, 7, 2 * 3 + 0 * 3 + 1], out[1, 11, 14, 1])


def _dots(jaxpr) -> list:
    """Every dot_general of a jaxpr, its sub-jaxprs' too (custom_vjp calls, pjit)."""
    found = []
    for e in jaxpr.eqns:
        if e.primitive.name == "dot_general":
            found.append(e)
        for sub in jax.extend.core.jaxprs_in_params(e.params):
            found += _dots(sub)
    return found


def test_bf16_products_keep_the_parameters_and_float32_values():
    """Actor and critic with bf16 products (the bf16 path's): the same parameters, float32
    outputs and gradients near the float32 networks', and every product, forward and of the
    gradient, reading bf16 operands into float32."""
    z = _normal(0, (4, 64))
    a = jnp.asarray(np.random.default_rng(1).uniform(-1, 1, (4, 6)), jnp.float32)
    for make, args in (
        (lambda **kw: networks.Actor(6, hidden_dim=32, **kw), (z,)),
        (lambda **kw: networks.Critic(hidden_dim=32, **kw), (z, a)),
    ):
        full, mixed = make(), make(products=jnp.bfloat16)
        params = jax.jit(full.init)(jax.random.key(2), *args)
        same = jax.jit(mixed.init)(jax.random.key(2), *args)
        for x, y in zip(jax.tree.leaves(params), jax.tree.leaves(same), strict=True):
            np.testing.assert_array_equal(x, y)
        want, got = full.apply(params, *args), mixed.apply(params, *args)
        for x, y in zip(jax.tree.leaves(want), jax.tree.leaves(got), strict=True):
            assert y.dtype == jnp.float32
            np.testing.assert_allclose(y, x, rtol=3e-2, atol=3e-3)
            assert not np.array_equal(y, x)  # rounded operands: not the float32 function

        def loss(module, p, z, rest=args[1:]):
            out = module.apply(p, z, *rest)
            return sum(jnp.sum(jnp.sin(o)) for o in jax.tree.leaves(out))

        dots = _dots(jax.make_jaxpr(functools.partial(loss, mixed))(params, z).jaxpr)
        assert len(dots) == (4 if len(args) == 1 else 7)  # trunk, then 3 layers (per head)
        grad = jax.grad(functools.partial(loss, mixed), argnums=(0, 1))
        grad_dots = _dots(jax.make_jaxpr(grad)(params, z).jaxpr)
        assert len(grad_dots) == 3 * len(dots)  # forward, then the input's and the weight's
        for e in dots + grad_dots:
            assert [v.aval.dtype for v in e.invars] == [jnp.bfloat16] * 2
            assert e.outvars[0].aval.dtype == jnp.float32
        # the gradients: float32, near those of JAX's own rule for the same rounded forward
        # products (float32 cotangents), yet not the same numbers
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(networks, "_mixed_dot", _jax_rule_dot)
            want = jax.grad(functools.partial(loss, mixed), argnums=(0, 1))(params, z)
        got = grad(params, z)
        for x, y in zip(jax.tree.leaves(want), jax.tree.leaves(got), strict=True):
            assert y.dtype == jnp.float32 and y.shape == x.shape
            np.testing.assert_allclose(y, x, atol=2e-2 * float(jnp.max(jnp.abs(x))))
        assert not all(
            np.array_equal(x, y) for x, y in zip(jax.tree.leaves(want), jax.tree.leaves(got))
        )


def _jax_rule_dot(x, w, dtype):
    """`networks._mixed_dot`'s function, differentiated by JAX's rule (float32 cotangents)."""
    return jnp.matmul(x.astype(dtype), w.astype(dtype), preferred_element_type=jnp.float32)


def test_bf16_products_of_encoder_and_decoder_stay_bf16():
    """The bf16 encoder's and decoder's own Linear layers stay bf16 products with bf16 results
    (an earlier version of the products' dtype made them float32: 3% slower on an H100)."""
    z = _normal(0, (1, 64))
    obs = jnp.zeros((1, 84, 84, 9), jnp.uint8)
    for module, x in (
        (networks.PoolEncoder(64, jnp.bfloat16), obs),
        (networks.PoolDecoder(3, jnp.bfloat16), z),
    ):
        p = jax.eval_shape(module.init, jax.random.key(0), x)  # the program, not its numbers
        eqns = jax.make_jaxpr(module.apply)(p, x).jaxpr.eqns
        dense = [e for e in eqns if e.primitive.name == "dot_general"][0]
        assert [v.aval.dtype for v in (*dense.invars, *dense.outvars)] == [jnp.bfloat16] * 3


@pytest.mark.parametrize("channels", [1, 8])
@pytest.mark.parametrize("stride, output_padding", [(1, 0), (2, 1), (4, 3)])
def test_transposed_convolutions_equal_pytorch_sizes_and_lax(stride, output_padding, channels):
    """Each decoder layer is PyTorch's ConvTranspose2d: (in-1)*stride + k + output_padding.

    Written per output phase, it must compute lax.conv_transpose with the same kernel and bias,
    and have the same gradients with respect to input, kernel and bias.
    """
    k = 4 if stride == 4 else 3
    x = _normal(0, (2, 9, 9, 5))
    layer = networks.ConvTranspose(7, k, stride, output_padding, channels=channels)
    params = {
        "kernel": _normal(1, (k, k, 5, 7)),
        "bias": _normal(2, (7,)),
    }
    init = layer.init(jax.random.key(1), x)["params"]
    assert jax.tree.map(jnp.shape, init) == jax.tree.map(jnp.shape, params)
    pad = (k - 1, k - 1 + output_padding)

    def reference(p, x):
        y = jax.lax.conv_transpose(
            x, p["kernel"], (stride, stride), (pad, pad), dimension_numbers=("NHWC", "HWIO", "NHWC")
        )
        return y + p["bias"]

    ours = lambda p, x: layer.apply({"params": p}, x)  # noqa: E731
    size = (9 - 1) * stride + k + output_padding
    out = ours(params, x)
    assert out.shape == (2, size, size, 7)
    np.testing.assert_allclose(out, reference(params, x), rtol=1e-5, atol=1e-4)
    if size % stride == 0:  # the output as its phases: the same numbers, laid out by phase
        phases = layer.apply({"params": params}, x, phases=True)
        np.testing.assert_array_equal(phases, networks.space_to_depth(out, stride))
    else:
        with pytest.raises(ValueError, match=f"side {size} is not whole"):
            layer.apply({"params": params}, x, phases=True)
    probe = _normal(3, out.shape)  # a random cotangent
    loss = lambda f: lambda p, x: jnp.sum(probe * f(p, x))  # noqa: E731
    grads, expected = (jax.grad(loss(f), argnums=(0, 1))(params, x) for f in (ours, reference))
    for g, e in zip(jax.tree.leaves(grads), jax.tree.leaves(expected)):
        np.testing.assert_allclose(g, e, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("stride, cin", [(2, 9), (1, 32)])
def test_convolution_is_flax_conv_with_or_without_channel_padding(stride, cin):
    """`networks.Conv` has nn.Conv's parameters, initial values and function, and the same
    gradients, with its channels zero-padded to multiples of 8 (as on GPUs) or not."""
    x = _normal(0, (2, 13, 13, cin))
    flax_conv = nn.Conv(
        32,
        (3, 3),
        strides=(stride, stride),
        padding="VALID",
        kernel_init=networks.CONV_INIT,
        bias_init=networks.ZEROS,
    )
    expected_params = flax_conv.init(jax.random.key(1), x)["params"]
    probe = _normal(2, flax_conv.apply({"params": expected_params}, x).shape)
    bias = _normal(3, (32,))
    for channels in (1, 8):
        ours = networks.Conv(32, stride, channels=channels)
        params = ours.init(jax.random.key(1), x)["params"]
        assert jax.tree.map(jnp.shape, params) == jax.tree.map(jnp.shape, expected_params)
        np.testing.assert_array_equal(params["kernel"], expected_params["kernel"])
        p = {**params, "bias": bias}
        fns = [lambda p, x, m=m: m.apply({"params": p}, x) for m in (ours, flax_conv)]
        np.testing.assert_allclose(fns[0](p, x), fns[1](p, x), rtol=1e-5, atol=1e-5)
        grads = [jax.grad(lambda p, x, f=f: jnp.sum(probe * f(p, x)), (0, 1))(p, x) for f in fns]
        for g, e in zip(jax.tree.leaves(grads[0]), jax.tree.leaves(grads[1])):
            np.testing.assert_allclose(g, e, rtol=1e-4, atol=1e-4)


def _torch_layout(path, kernel):
    """A kernel as PyTorch's `orthogonal_` flattens it: Linear [out, in]; Conv2d
    [out, in*kh*kw]; ConvTranspose2d [in, out*kh*kw]."""
    name = "/".join(str(getattr(k, "key", k)) for k in path)
    if kernel.ndim == 2:
        return kernel.T, 1.0
    kh, kw, cin, cout = kernel.shape
    if "ConvTranspose" in name:
        return kernel.transpose(2, 3, 0, 1).reshape(cin, cout * kh * kw), np.sqrt(2)
    return kernel.transpose(3, 2, 0, 1).reshape(cout, cin * kh * kw), np.sqrt(2)


@pytest.mark.parametrize("method", ["dear", "sear"])
def test_initialisation_is_pytorchs_orthogonal_on_its_layouts(method):
    """Every weight, flattened as PyTorch flattens it, has all singular values equal to its
    gain (1 for linear layers, sqrt(2) for convolutions and transposed convolutions): the
    transposed convolutions of the decoders included, whose scale differs when the
    orthogonal matrix is drawn on Flax's kernel layout instead. Biases start at zero."""
    # Narrow widths keep the QR decompositions of the initialiser cheap on a CPU; the decoder
    # keeps the reference's channel widths.
    cfg = AgentConfig(action_dim=6, method=method, latent_dim=256, hidden_dim=64)
    params = init_params(cfg, jax.random.key(1))
    checked = 0
    for path, leaf in jax.tree_util.tree_leaves_with_path(params):
        if path[-1].key == "kernel":
            matrix, gain = _torch_layout(path, np.asarray(leaf, np.float64))
            singular = np.linalg.svd(matrix, compute_uv=False)
            np.testing.assert_allclose(singular, gain, rtol=1e-4, err_msg=str(path))
            checked += 1
        elif path[-1].key == "bias" and "LayerNorm" not in str(path):
            assert not np.any(np.asarray(leaf)), path
    assert checked >= 20


@pytest.mark.parametrize("shape, k", [((2, 35, 35, 8), 4), ((3, 9, 10, 4), 3)])
def test_avg_pool_is_flax_avg_pool_in_values_and_gradients(shape, k):
    """The reshape-and-mean pool is flax's VALID average pool (windows past the edge dropped),
    and its gradient too: 1/k^2 on every pixel of a whole window, 0 on the dropped ones."""
    x = _normal(0, shape)
    ct = _normal(1, (shape[0], shape[1] // k, shape[2] // k, shape[3]))

    def flax_pool(x):
        return nn.avg_pool(x, (k, k), strides=(k, k), padding="VALID")

    np.testing.assert_allclose(networks.avg_pool(x, k), flax_pool(x), rtol=1e-6, atol=1e-6)
    got = jax.vjp(lambda x: networks.avg_pool(x, k), x)[1](ct)[0]
    want = jax.vjp(flax_pool, x)[1](ct)[0]
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    assert float(jnp.abs(got[:, :, shape[2] // k * k :]).max()) == 0.0
    np.testing.assert_allclose(got[0, :k, :k, 0], ct[0, 0, 0, 0] / k**2, rtol=1e-6)


def test_pixels_are_centred():
    x = networks.preprocess(jnp.array([0, 255], jnp.uint8))
    np.testing.assert_allclose(x, [-0.5, 0.5])
    np.testing.assert_allclose(
        networks.preprocess(jnp.array([128], jnp.uint8)), [128 / 255 - 0.5], atol=1e-7
    )


def test_trunk_with_tensor_core_channels_is_the_same_function():
    """The conv trunk as GPUs run it in bf16 (pixels kept apart by a barrier, channels padded to
    8) computes what the plain trunk computes, gradients included (here in float32)."""
    obs = _pixels(0, (2, 84, 84, 9))
    plain, padded = networks.ConvTrunk(channels=1), networks.ConvTrunk(channels=8)
    params = plain.init(jax.random.key(1), obs)
    assert jax.tree.map(jnp.shape, params) == jax.tree.map(
        jnp.shape, padded.init(jax.random.key(1), obs)
    )
    loss = lambda m: lambda p: jnp.sum(jnp.sin(m.apply(p, obs)))  # noqa: E731
    np.testing.assert_allclose(loss(padded)(params), loss(plain)(params), rtol=1e-5)
    for g, e in zip(*(jax.tree.leaves(jax.grad(loss(m))(params)) for m in (padded, plain))):
        np.testing.assert_allclose(g, e, rtol=1e-4, atol=1e-4)


def _vmapped_decoder_and_encoder(seeds: int, batch: int):
    """(params, z, obs, f): a mask decoder and a conv trunk per seed, and f = vmap over seeds of
    the value and gradient (in params and z) of a loss that reads both networks' outputs."""
    dec, enc = networks.PoolDecoder(3), networks.ConvTrunk()
    z = _normal(0, (seeds, batch, 8))
    obs = _pixels(1, (seeds, batch, 84, 84, 9))
    # one seed after another (as update.init_seeds): vmapped, XLA:CPU may run the batched QR
    # decompositions of the orthogonal inits at once, and deadlock on 2 cores
    params = jax.jit(
        lambda keys: jax.lax.map(lambda k: (dec.init(k, z[0]), enc.init(k, obs[0])), keys)
    )(jax.random.split(jax.random.key(2), seeds))

    def loss(p, z, obs):
        return jnp.sum(jnp.sin(dec.apply(p[0], z))) + jnp.sum(jnp.cos(enc.apply(p[1], obs)))

    return params, z, obs, jax.vmap(jax.value_and_grad(loss, argnums=(0, 1)))


def test_seed_looped_convs_are_vmap_without_grouped_convolutions():
    """Under `conv_settings(loop_seeds=True)`, a vmapped decoder (transposed convolutions) and
    encoder give vmap's values and gradients, computed by one ungrouped convolution per seed,
    forward and backward, where plain vmap makes grouped ones."""
    seeds = 3
    params, z, obs, grads = _vmapped_decoder_and_encoder(seeds, 2)

    def looped(p, z, obs):
        with networks.conv_settings(loop_seeds=True):
            return grads(p, z, obs)

    want, got = jax.jit(grads)(params, z, obs), jax.jit(looped)(params, z, obs)
    assert networks._CONV.get() == networks.ConvSettings()  # the context was left
    for a, b in zip(jax.tree.leaves(want), jax.tree.leaves(got)):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-4)

    def group_counts(fn):
        text = jax.jit(fn).lower(params, z, obs).as_text()
        return [int(n) for n in re.findall(r"(?:feature|batch)_group_count = (\d+)", text)]

    assert max(group_counts(grads)) == seeds  # vmap's grouped convolutions
    counts = group_counts(looped)
    # 4 decoder + 4 encoder convolutions: forward, filter gradient, and input gradient (not of
    # the pixels), each once per seed, all ungrouped (the decoder's stride-4 first layer, one
    # 1x1 convolution per output phase, is a matrix product).
    assert set(counts) == {1} and len(counts) == 2 * seeds * (8 + 8 + 7)


def test_pallas_filter_gradient_equals_cudnns():
    """`dear_jax.wgrad.filter_gradient` (Pallas; here its interpreter) is the filter gradient
    of a stride-1 VALID convolution: kernel sizes 1-3 and the decoder's channel counts, one
    image per program or several; under vmap (one launch for all indices) too."""
    from dear_jax import wgrad

    def cudnn(x, g, k):
        conv = lambda w: networks._plain_conv(x, w, 1)  # noqa: E731
        return jax.vjp(conv, jnp.zeros((k, k, x.shape[-1], g.shape[-1]), x.dtype))[1](g)[0]

    for n, size, c, f, k, images in (
        (2, 11, 16, 32, 3, 1),
        (4, 9, 32, 16, 2, 2),
        (3, 5, 16, 256, 1, 3),
    ):
        x = _normal(size, (n, size, size, c))
        g = _normal(size + 1, (n, size - k + 1, size - k + 1, f))
        assert wgrad.supported(x.shape, (k, k, c, f), 1)
        # jitted: an eager pallas_call builds its kernel anew, and compiles it, on every call
        ours = jax.jit(wgrad.filter_gradient, static_argnums=2, static_argnames="images")
        np.testing.assert_allclose(
            ours(x, g, k, images=images), cudnn(x, g, k), rtol=1e-5, atol=1e-4
        )
    stacked = jax.jit(jax.vmap(lambda x, g: wgrad.filter_gradient(x, g, 3)))
    xs = _normal(1, (2, 2, 7, 7, 16))
    gs = _normal(2, (2, 2, 5, 5, 32))
    both = stacked(xs, gs)
    for i in range(2):
        np.testing.assert_allclose(both[i], cudnn(xs[i], gs[i], 3), rtol=1e-5, atol=1e-4)
    assert not wgrad.supported((2, 11, 11, 16), (3, 3, 16, 32), 2)  # stride 2 stays on cuDNN
    assert not wgrad.supported((2, 11, 11, 12), (3, 3, 12, 32), 1)  # 12 channels: not a power of 2
    with pytest.raises(ValueError, match="not the gradient"):
        wgrad.filter_gradient(xs[0], gs[0][:, :4], 3)


def test_pallas_filter_gradient_lowers_for_cuda_as_one_triton_kernel():
    """Compiled (not interpreted), the kernel lowers for CUDA on any machine, through Pallas'
    Triton backend: JAX's default GPU backend, Mosaic GPU, refused it (shared memory), and
    Triton's lowering refused Python's integer `//`. Under vmap it stays one launch."""
    from dear_jax import wgrad

    x = jax.ShapeDtypeStruct((2, 8, 41, 41, 32), jnp.bfloat16)  # 2 seeds
    g = jax.ShapeDtypeStruct((2, 8, 39, 39, 32), jnp.bfloat16)
    fn = jax.vmap(lambda x, g: wgrad.filter_gradient(x, g, 3, interpret=False))
    text = jax.jit(fn).trace(x, g).lower(lowering_platforms=("cuda",)).as_text()
    assert text.count("xla.gpu.triton") == 1


@pytest.mark.parametrize("loop_seeds", [False, True])
def test_networks_with_pallas_filter_gradients_are_the_same_function(loop_seeds):
    """With filter_gradient="pallas" the decoder and the encoder (stride 2 first: cuDNN) give the
    values and gradients of the plain convolutions, vmapped over seeds with and without
    loop_seeds."""
    params, z, obs, grads = _vmapped_decoder_and_encoder(2, 1)

    def pallas(p, z, obs):
        with networks.conv_settings(loop_seeds=loop_seeds, filter_gradient="pallas"):
            return grads(p, z, obs)

    ours = jax.jit(pallas)
    text = ours.lower(params, z, obs).as_text()
    assert "triton" in text or "pallas" in text  # the kernel is in the program
    want, got = jax.jit(grads)(params, z, obs), ours(params, z, obs)
    for a, b in zip(jax.tree.leaves(want), jax.tree.leaves(got)):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-4)
    with pytest.raises(ValueError, match="unknown filter_gradient"):
        with networks.conv_settings(filter_gradient="cutlass"):
            pass
