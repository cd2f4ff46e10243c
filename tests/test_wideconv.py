"""dear_jax.wideconv: stride-1 conv stacks as Pallas kernels (here in Pallas' interpreter)."""

import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dear_jax import augment, networks, update, wideconv


def _lax_stack(x, layers, pads, relu_last=True, stride=1):
    x = x.astype(jnp.float32)
    for i, ((k, b), p) in enumerate(zip(layers, pads)):
        x = jnp.pad(x, ((0, 0), (p, p), (p, p), (0, 0)))
        s = (stride, stride) if i == 0 else (1, 1)
        x = jax.lax.conv_general_dilated(
            x, k, s, "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"), precision="highest"
        )
        x = x + b
        if relu_last or i < len(layers) - 1:
            x = jax.nn.relu(x)
    return x


# Inputs are drawn with NumPy: jax.random compiles a program per shape (seconds each).
def _normal(seed, shape, scale=1.0):
    return jnp.asarray(np.random.default_rng(seed).normal(0, scale, shape), jnp.float32)


def _pixels(seed, shape):
    return jnp.asarray(np.random.default_rng(seed).integers(0, 256, shape, np.uint8))


def _bernoulli(seed, p, shape):
    return jnp.asarray(np.random.default_rng(seed).uniform(size=shape) < p)


def _layers(seed, kernels, channels, lead=()):
    rng = np.random.default_rng(seed)
    return tuple(
        (
            jnp.asarray(rng.normal(0, 0.2, (*lead, k, k, c, f)), jnp.float32),
            jnp.asarray(rng.normal(0, 0.1, (*lead, f)), jnp.float32),
        )
        for k, c, f in zip(kernels, channels, channels[1:])
    )


# (input size, kernel sizes, pads, channels, ReLU after the last layer, first layer's stride,
# random shift's pad)
STACKS = dict(
    # the encoder: a stride-2 layer on 9-channel uint8 pixels, then 3x3 VALID layers
    encoder=(13, (3, 3, 3), (0, 0, 0), (9, 16, 32, 16), True, 2, 0),
    # the same reading the pixels through DrQ-v2's random shift
    encoder_shifted=(13, (3, 3, 3), (0, 0, 0), (9, 16, 32, 16), True, 2, 3),
    # the decoder: transposed 3x3 layers (pad 2), then the 2x2 layer of the output phases
    decoder=(5, (3, 3, 2), (2, 2, 1), (16, 32, 16, 16), False, 1, 0),
)


def _case(name):
    """A STACKS case: (its input, its layers, each image's crop offsets with the shift's
    extremes among them (edge pixels repeated), conv_stack of (x, layers) as the case computes
    it, the arguments that get gradients: an integer input gets none)."""
    size, kernels, pads, channels, relu_last, stride, shift = STACKS[name]
    pixels = stride > 1
    shape = (2, size, size, channels[0])
    x = _pixels(0, shape) if pixels else _normal(0, shape)
    crops = jnp.array([[0, 2 * shift], [shift + 1, 1]]) if shift else None
    dtype = jnp.float32 if pixels else None

    def stack(x, ws):
        return wideconv.conv_stack(x, ws, pads, relu_last, dtype, stride, shift, crops)

    return x, _layers(1, kernels, channels), crops, stack, 1 if pixels else (0, 1)


@pytest.mark.parametrize("name", STACKS)
def test_conv_stack_is_convolutions_in_values_and_gradients(monkeypatch, name):
    """Encoder-like and decoder-like stacks: the values and every gradient (input, kernels,
    biases) of lax's convolutions; an integer input gets no gradient."""
    monkeypatch.setattr(wideconv, "BLOCK", 16)
    # Compiled on a GPU, the kernels' float32 dots run in IEEE float32 here, as the reference
    # does: in TF32, the values differ by ~1e-3, and where a pre-activation near zero takes the
    # other side of its ReLU, a gradient differs by much more.
    monkeypatch.setattr(wideconv, "PRECISION", jax.lax.Precision.HIGHEST)
    size, kernels, pads, channels, relu_last, stride, shift = STACKS[name]
    x, layers, crops, ours, argnums = _case(name)
    assert wideconv.supported(x, layers, pads, stride, shift)

    def shifted(x):
        return augment.Crops(crops, shift, "gather").apply(x) if shift else x

    def theirs(x, ws):
        return _lax_stack(shifted(x), ws, pads, relu_last, stride)

    want = jax.jit(theirs)(x, layers)
    scale = float(jnp.abs(want).max())
    # The output and the gradients of sum(sin(output / scale)), each stack one program: the
    # kernels are compiled once, for the values, the gradients and the dead layers below.
    ours_and_grads = _value_and_grad(ours, argnums, scale)
    (_, got), got_grads = ours_and_grads(x, layers)
    (_, want), want_grads = _value_and_grad(theirs, argnums, scale)(x, layers)
    out = (
        (size + 2 * pads[0] - kernels[0]) // stride
        + 1
        + sum(2 * p - k + 1 for k, p in zip(kernels[1:], pads[1:]))
    )
    assert got.shape == want.shape == (2, out, out, channels[-1])
    assert got.dtype == jnp.float32
    tol = 1e-5 if wideconv._interpret() else 1e-4
    np.testing.assert_allclose(got / scale, want / scale, rtol=tol, atol=tol)
    for a, b in zip(jax.tree.leaves(got_grads), jax.tree.leaves(want_grads), strict=True):
        np.testing.assert_allclose(a, b, rtol=10 * tol, atol=10 * tol)
    if relu_last:
        # The ReLU gradient is applied: a stack whose pre-activations are all negative passes none.
        dead = tuple((k, b - 1e4) for k, b in layers)
        _, grads = ours_and_grads(x, dead)
        assert all(float(jnp.abs(g).max()) == 0.0 for g in jax.tree.leaves(grads))


@pytest.mark.parametrize(
    "name, settings",
    [
        ("decoder", {"TAP_LOOP": False, "WGRAD_ANCHORS": False}),
        ("encoder_shifted", {"TAP_LOOP": False, "WGRAD_G_FIRST": True}),
    ],
)
def test_kernel_settings_compute_the_same(monkeypatch, name, settings):
    """The kernels' settings change how, not what: a convolution's taps as a loop (traced tap
    indices, every padding check at run time) or unrolled (the checks a tap needs, fixed);
    filter gradients as x^T g or g^T x, over output rows or over anchors (padded and VALID
    layers; steps of 16 rows, 2 per program, so that steps and programs begin inside images).
    The same values and gradients as the defaults."""
    monkeypatch.setattr(wideconv, "BLOCK", 16)
    monkeypatch.setattr(wideconv, "WGRAD_BLOCK", 16)
    monkeypatch.setattr(wideconv, "WGRAD_STEPS", 2)
    monkeypatch.setattr(wideconv, "PRECISION", jax.lax.Precision.HIGHEST)
    x, layers, _, stack, argnums = _case(name)
    default = _value_and_grad(stack, argnums, 1.0)(x, layers)
    for setting, value in settings.items():
        assert getattr(wideconv, setting) != value
        monkeypatch.setattr(wideconv, setting, value)
    changed = _value_and_grad(stack, argnums, 1.0)(x, layers)
    # float32 sums in another order: equal to rounding, relative to each array's largest value
    for a, b in zip(jax.tree.leaves(changed), jax.tree.leaves(default), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * max(1.0, float(np.abs(b).max())))


def _value_and_grad(stack, argnums, scale):
    """jit of (x, layers) -> ((sum(sin(stack(x, layers) / scale)), stack(x, layers)), the
    gradients of that sum)."""

    def loss(x, ws):
        y = stack(x, ws)
        return jnp.sum(jnp.sin(y / scale)), y

    return jax.jit(jax.value_and_grad(loss, argnums, has_aux=True))


@pytest.mark.parametrize(
    "phase, shift, loss", [(2, 4, "bce"), (1, 0, "bce"), (2, 4, "clipped_squares")]
)
def test_conv_stack_loss_is_the_loss_of_the_stacks_output(monkeypatch, phase, shift, loss):
    """The fused loss is the decoder's loss (summed over images) of conv_stack's output against
    the targets laid out as the last layer's phases (read through a random shift, its extreme
    offsets included), in value and in every gradient; the output's lanes past the targets'
    get no loss. The mask's BCE takes {0, 1} labels, the reconstruction uint8 pixels."""
    monkeypatch.setattr(wideconv, "BLOCK", 16)
    monkeypatch.setattr(wideconv, "PRECISION", jax.lax.Precision.HIGHEST)
    x = _normal(0, (2, 5, 5, 16))
    layers = _layers(1, (3, 3, 2), (16, 32, 16, 16))
    pads = (2, 2, 1)  # sides 5 -> 7 -> 9 -> 10
    side = 10 * phase
    shape = (2, side, side, 3)
    targets = _bernoulli(2, 0.3, shape).astype(jnp.uint8) if loss == "bce" else _pixels(2, shape)
    crops = jnp.array([[0, 2 * shift], [shift + 1, 1]]) if shift else None
    lanes = phase**2 * 3

    def ours(x, ws):
        return wideconv.conv_stack_loss(x, ws, targets, pads, None, phase, shift, crops, loss)

    def output(x, ws):
        return wideconv.conv_stack(x, ws, pads, False)[..., :lanes]

    def theirs(x, ws):
        y = augment.Crops(crops, shift, "gather").apply(targets) if shift else targets
        y = networks.space_to_depth(y, phase)
        return 2 * networks.DECODER_LOSSES[loss](output(x, ws), y)  # a mean over 2 images

    if loss == "clipped_squares":  # the clip both passes and stops gradients here
        out = np.abs(jax.jit(output)(x, layers))
        assert (out < 0.5).mean() > 0.05 and (out > 0.5).mean() > 0.05
    # c * the loss, for the cotangents c = 1 and 2: one program, compiled once
    scaled = jax.jit(jax.value_and_grad(lambda x, ws, c: c * ours(x, ws), (0, 1)))
    value, got = scaled(x, layers, 1.0)
    want_value, want = jax.jit(jax.value_and_grad(theirs, (0, 1)))(x, layers)
    np.testing.assert_allclose(value, want_value, rtol=1e-5)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        scale = float(jnp.abs(b).max())
        np.testing.assert_allclose(a / scale, b / scale, atol=1e-5)
    # the cotangent scales every gradient (it is folded into the last layer's)
    _, double = scaled(x, layers, 2.0)
    for a, b in zip(jax.tree.leaves(double), jax.tree.leaves(got), strict=True):
        np.testing.assert_allclose(a, 2 * b, rtol=1e-6, atol=1e-6)
    if loss != "bce":
        return
    small = targets[:, 1:, 1:]
    with pytest.raises(ValueError, match=rf"targets \(2, {side - 1}, .* match.*10 x 10 x 16"):
        wideconv.conv_stack_loss(x, layers, small, pads, None, phase, shift, crops)
    wide = jnp.zeros((2, side, side, 5), jnp.uint8)  # phase**2 * 5 lanes: more than 16 if phased
    if phase == 2:
        with pytest.raises(ValueError, match="do not match"):
            wideconv.conv_stack_loss(x, layers, wide, pads, None, phase, shift, crops)
    else:
        with pytest.raises(ValueError, match=r"a shift needs crop offsets of shape \(2, 2\)"):
            wideconv.conv_stack_loss(x, layers, targets, pads, None, phase, 4, None)
    with pytest.raises(ValueError, match=r"unknown loss 'l1'; valid: \['bce', 'clipped_squares'\]"):
        wideconv.conv_stack_loss(x, layers, targets, pads, None, phase, shift, crops, "l1")


def test_conv_stack_loss_under_vmap_is_each_seed_on_its_own(monkeypatch):
    """Vmapped over seeds, each with its own weights, bool labels, crops and cotangent: every
    seed's loss and gradients are those of its stack alone, times its cotangent."""
    monkeypatch.setattr(wideconv, "BLOCK", 16)
    x = _normal(3, (2, 2, 5, 5, 16))
    layers = _layers(4, (3, 2), (16, 16, 16), lead=(2,))
    labels = _bernoulli(5, 0.4, (2, 2, 16, 16, 3))
    crops = jnp.array([[[0, 8], [3, 1]], [[8, 8], [4, 0]]])
    weights = jnp.array([1.0, 3.0])

    def bce(x, ws, labels, crops):
        return wideconv.conv_stack_loss(x, ws, labels, (2, 1), None, 2, 4, crops)

    def weighted(x, ws):
        return jnp.sum(weights * jax.vmap(bce)(x, ws, labels, crops))

    loss, grads = jax.jit(jax.value_and_grad(weighted, (0, 1)))(x, layers)
    one = jax.jit(jax.value_and_grad(bce, (0, 1)))  # compiled once, for both seeds
    alone = [
        one(x[s], jax.tree.map(lambda a, s=s: a[s], layers), labels[s], crops[s]) for s in range(2)
    ]
    np.testing.assert_allclose(loss, sum(w * a[0] for w, a in zip(weights, alone)), rtol=1e-6)
    for s, w in enumerate(weights):
        for a, b in zip(jax.tree.leaves(grads), jax.tree.leaves(alone[s][1]), strict=True):
            np.testing.assert_allclose(a[s], w * b, rtol=1e-5, atol=1e-5)


def test_conv_stack_under_vmap_is_each_seed_on_its_own():
    """Vmapped over seeds (each with its own weights), bf16 activations: every seed's values and
    gradients equal the same stack run for that seed alone."""
    x = _normal(1, (2, 2, 7, 7, 16)).astype(jnp.bfloat16)
    layers = _layers(2, (3, 2), (16, 16, 16), lead=(2,))

    def f(x, ws):
        return jnp.sum(wideconv.conv_stack(x, ws, (0, 1), False).astype(jnp.float32) ** 2)

    both = jax.jit(jax.vmap(jax.value_and_grad(f, (0, 1))))(x, layers)
    one = jax.jit(jax.value_and_grad(f, (0, 1)))  # compiled once, for both seeds
    for s in range(2):
        alone = one(x[s], jax.tree.map(lambda a, s=s: a[s], layers))
        for a, b in zip(jax.tree.leaves(both), jax.tree.leaves(alone), strict=True):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(np.asarray(a[s], np.float32), np.asarray(b, np.float32))


def _filter_gradient_grids(fn, *args) -> list[tuple[int, ...]]:
    """The grids of the filter-gradient kernels (those whose first output holds one [c, f]
    matrix per program and tap) in the program of fn(*args), traced, not run."""
    grids = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "pallas_call":
                mapping = eqn.params["grid_mapping"]
                if eqn.outvars[0].aval.ndim - len(mapping.vmapped_dims) == 4:
                    grids.append(tuple(mapping.grid))
                continue
            for param in eqn.params.values():
                for sub in param if isinstance(param, (tuple, list)) else (param,):
                    sub = getattr(sub, "jaxpr", sub)
                    if hasattr(sub, "eqns"):
                        walk(sub)

    walk(jax.make_jaxpr(fn)(*args).jaxpr)
    return grids


def test_filter_gradient_programs_follow_the_number_of_seeds(monkeypatch):
    """With WGRAD_MIN_PROGRAMS set, a filter gradient's programs on GPUs take fewer steps when
    few seeds are vmapped, so that its grid keeps that many programs; five seeds keep 32 steps.
    The encoder's 35 x 35 layer at batch 512: 663,040 anchors (512 x 37 x 35), 324 programs of
    32 steps of 64 rows, 1,295 of 8."""
    monkeypatch.setattr(wideconv, "INTERPRET", False)  # traced only
    monkeypatch.setattr(wideconv, "WGRAD_MIN_PROGRAMS", 1024)
    assert (wideconv.WGRAD_STEPS, wideconv.WGRAD_BLOCK) == (32, 64)
    layers = lambda seeds: (  # noqa: E731
        (
            jax.ShapeDtypeStruct((seeds, 3, 3, 32, 32), jnp.float32),
            jax.ShapeDtypeStruct((seeds, 32), jnp.float32),
        ),
    )

    def loss(x, ws):
        return jnp.sum(wideconv.conv_stack(x, ws, 0, True, jnp.bfloat16).astype(jnp.float32))

    grad = jax.vmap(jax.grad(loss, 1))
    # (a vmapped axis of size 1 is no grid axis)
    for seeds, grid in ((1, (1295,)), (2, (2, 648)), (5, (5, 324))):
        x = jax.ShapeDtypeStruct((seeds, 512, 37, 37, 32), jnp.bfloat16)
        assert _filter_gradient_grids(grad, x, layers(seeds)) == [grid]
    # lanes x seeds: both vmapped axes count; not vmapped, one image set alone
    x = jax.ShapeDtypeStruct((2, 2, 512, 37, 37, 32), jnp.bfloat16)
    ws = jax.tree.map(lambda a: jax.ShapeDtypeStruct((2, *a.shape), a.dtype), layers(2))
    assert _filter_gradient_grids(jax.vmap(grad), x, ws) == [(2, 2, 324)]
    x = jax.ShapeDtypeStruct((512, 37, 37, 32), jnp.bfloat16)
    one = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype), layers(1))
    assert _filter_gradient_grids(jax.grad(loss, 1), x, one) == [(1295,)]
    monkeypatch.setattr(wideconv, "WGRAD_MIN_PROGRAMS", 0)
    assert _filter_gradient_grids(jax.grad(loss, 1), x, one) == [(324,)]


def test_filter_gradients_of_any_steps_are_the_same_under_nested_vmap(monkeypatch):
    """Lanes x seeds vmapped, with steps that differ with the vmapped sizes: every lane's and
    seed's gradients are those of its stack alone (taken with other steps)."""
    monkeypatch.setattr(wideconv, "BLOCK", 16)
    monkeypatch.setattr(wideconv, "WGRAD_BLOCK", 16)
    monkeypatch.setattr(wideconv, "PRECISION", jax.lax.Precision.HIGHEST)
    steps_of = wideconv._wgrad_steps
    monkeypatch.setattr(wideconv, "_wgrad_steps", lambda rows, batch: 8 // batch)
    x = _normal(6, (2, 2, 2, 7, 7, 16))
    layers = _layers(7, (3, 2), (16, 32, 16), lead=(2, 2))

    def f(x, ws):
        return jnp.sum(jnp.sin(wideconv.conv_stack(x, ws, (0, 1), True)))

    nested = jax.jit(jax.vmap(jax.vmap(jax.grad(f, (0, 1)))))(x, layers)
    one = jax.jit(jax.grad(f, (0, 1)))  # 8 steps per program, against 2 when nested
    for i in range(2):
        for j in range(2):
            alone = one(x[i, j], jax.tree.map(lambda a, i=i, j=j: a[i, j], layers))
            for a, b in zip(jax.tree.leaves(nested), jax.tree.leaves(alone), strict=True):
                np.testing.assert_allclose(a[i, j], b, rtol=1e-5, atol=1e-5)
    # A filter gradient whose input is shared by the vmapped seeds (unbatched), its output
    # gradients not: each seed's is its own.
    layer = wideconv._Pass(images=2, size_in=7, size=5, kernel=3, pad=0)
    acts = wideconv._Grid(2, 7).flatten(x[0, 0])
    grads = jnp.stack([layer.out.flatten(_normal(8 + s, (2, 5, 5, 32))) for s in range(2)])
    shared = jax.jit(jax.vmap(lambda g: wideconv._wgrad(acts, g, layer)))(grads)
    for s in range(2):
        alone = jax.jit(lambda g: wideconv._wgrad(acts, g, layer))(grads[s])
        for a, b in zip(shared, alone, strict=True):
            np.testing.assert_allclose(a[s], b, rtol=1e-5, atol=1e-5)
    # 10^5 rows in steps of 16: 196 programs of 32 steps; >= 1,024 programs over 1 / 3 / 16
    # vmapped copies take 4 / 16 / 32 steps, on GPUs only
    monkeypatch.setattr(wideconv, "WGRAD_MIN_PROGRAMS", 1024)
    assert steps_of(10**5, 1) == 32  # the interpreter: always WGRAD_STEPS
    monkeypatch.setattr(wideconv, "INTERPRET", False)
    assert (steps_of(10**5, 1), steps_of(10**5, 3), steps_of(10**5, 16)) == (4, 16, 32)


def test_kernel_constants_hold_inside_their_block_only():
    """`wideconv.constants` sets the named constants (a switch keeps its bool type) for the
    block, and restores them after it, also when it raises; bad settings name the problem."""
    before = (wideconv.WGRAD_STEPS, wideconv.TAP_LOOP, wideconv.BLOCK)
    with wideconv.constants("WGRAD_STEPS=8, TAP_LOOP=0"):
        assert (wideconv.WGRAD_STEPS, wideconv.TAP_LOOP, wideconv.BLOCK) == (8, False, before[2])
        assert wideconv.TAP_LOOP is False
    assert (wideconv.WGRAD_STEPS, wideconv.TAP_LOOP, wideconv.BLOCK) == before
    with pytest.raises(RuntimeError), wideconv.constants({"BLOCK": 64}):
        assert wideconv.BLOCK == 64
        raise RuntimeError
    assert wideconv.BLOCK == before[2]
    assert wideconv.parse_constants("") == {}
    with pytest.raises(ValueError, match=r"'BLOK=64': give NAME=INT with NAME one of BLOCK, "):
        wideconv.parse_constants("BLOK=64")
    with pytest.raises(ValueError, match="'PRECISION=1': give NAME=INT"):  # not an integer one
        wideconv.parse_constants("PRECISION=1")
    with pytest.raises(ValueError, match="'BLOCK=big': 'big' is not an integer"):
        wideconv.parse_constants("BLOCK=big")
    assert wideconv.parse_constants(" BLOCK = 64 ,WGRAD_MIN_PROGRAMS=0") == {
        "BLOCK": 64,
        "WGRAD_MIN_PROGRAMS": 0,
    }
    for bad, why in [
        ("BLOCK=96", "BLOCK must be a power of two"),
        ("WGRAD_STEPS=0", "WGRAD_STEPS must be a power of two"),
        ("TAP_LOOP=7", "TAP_LOOP is a switch, 0 or 1"),
        ("CONV_STAGES=0", "CONV_STAGES must be at least 1"),
        ("WGRAD_MIN_PROGRAMS=-1", "WGRAD_MIN_PROGRAMS must be at least 0"),
    ]:
        with pytest.raises(ValueError, match=why):
            wideconv.parse_constants(bad)
    with pytest.raises(ValueError, match="'jax=1': give NAME=INT"), wideconv.constants({"jax": 1}):
        pass
    with pytest.raises(ValueError, match="'BLOCK': give NAME=INT"):
        update.AgentConfig(action_dim=6, kernels="BLOCK")


def test_the_update_is_traced_with_its_configs_kernel_constants(monkeypatch):
    """AgentConfig.kernels holds while the update is traced, for its backward pass too: with
    WGRAD_MIN_PROGRAMS=1024 a lone seed's filter gradients (batch 8: 10,360 anchors at 35 x 35)
    take 1 step per program rather than 32, and the module's value is back after."""
    monkeypatch.setattr(wideconv, "INTERPRET", False)  # traced only
    small = dict(action_dim=2, latent_dim=64, hidden_dim=32, feature_dim=8, conv_stack="pallas")
    batch = 8
    images = jax.ShapeDtypeStruct((batch, 84, 84, 9), jnp.uint8)
    data = update.Batch(
        obs=images,
        action=jax.ShapeDtypeStruct((batch, 2), jnp.float32),
        reward=jax.ShapeDtypeStruct((batch,), jnp.float32),
        discount=jax.ShapeDtypeStruct((batch,), jnp.float32),
        next_obs=images,
        mask=jax.ShapeDtypeStruct((batch, 84, 84, 3), jnp.uint8),
    )

    def grids(kernels):
        cfg = update.AgentConfig(method="dear", kernels=kernels, **small)
        state = jax.eval_shape(functools.partial(update.init, cfg), jax.random.key(0))
        fn = functools.partial(update.update, cfg=cfg)
        return _filter_gradient_grids(fn, state, data, jax.random.key(1), update.HParams())

    default, many = grids(""), grids("WGRAD_MIN_PROGRAMS=1024")
    assert wideconv.WGRAD_MIN_PROGRAMS == 0
    # the encoder's 4 layers and the mask decoder's 4 Pallas layers
    assert len(default) == len(many) == 8
    assert (6,) in default and (162,) in many  # 35 x 35: ceil(10,360 / 64 / steps)
    assert all(m[0] > d[0] for d, m in zip(default, many))


def test_supported_shapes():
    k = lambda c, f, n=3: (jnp.zeros((n, n, c, f)), jnp.zeros(f))  # noqa: E731
    x = lambda *shape, dtype=jnp.bfloat16: jax.ShapeDtypeStruct(shape, dtype)  # noqa: E731
    pixels = x(2, 84, 84, 9, dtype=jnp.uint8)
    assert wideconv.supported(x(2, 41, 41, 32), (k(32, 32),) * 3, 0)
    assert wideconv.supported(pixels, (k(9, 32),) + (k(32, 32),) * 3, 0, stride=2)
    assert wideconv.supported(x(2, 35, 35, 16), (k(16, 32), k(32, 32), k(32, 16, 2)), (2, 2, 1))
    assert not wideconv.supported(x(2, 41, 41, 12), (k(12, 32),), 0)  # 12: not a power of 2
    assert not wideconv.supported(x(2, 41, 40, 32), (k(32, 32),), 0)  # not square
    assert not wideconv.supported(x(2, 41, 41, 32), (k(32, 32),), 3)  # pad as wide as the kernel
    assert not wideconv.supported(x(2, 41, 41, 32), (k(16, 32),), 0)  # kernel's channels differ
    assert not wideconv.supported(x(2, 5, 5, 32), (k(32, 32),) * 3, 0)  # nothing left: 5 -> -1
    # a 3x3 layer padded by 1 keeps the size (its taps past the edges read zeros)
    assert wideconv.supported(x(2, 9, 9, 32), (k(32, 32),), 1)
    assert not wideconv.supported(x(2, 9, 9, 32), (k(32, 32),) * 2, (0,))  # one pad, two layers
    # a strided first layer reads integer pixels of at most 16 channels, unpadded
    assert not wideconv.supported(x(2, 84, 84, 9), (k(9, 32),), 0, stride=2)
    assert not wideconv.supported(x(2, 84, 84, 32, dtype=jnp.uint8), (k(32, 32),), 0, stride=2)
    assert not wideconv.supported(pixels, (k(9, 32),), 1, stride=2)


def test_stacks_lower_for_cuda_as_one_triton_kernel_per_layer_and_pass(monkeypatch):
    """Compiled (not interpreted) on any machine: forward, input gradient and filter gradient
    of each layer are one Triton kernel each, for all vmapped seeds; the uint8 input of the
    encoder's stack, read through the random shift, gets no input gradient, and neither an
    edge-padded nor a float copy of its pixels is made outside the kernels."""
    monkeypatch.setattr(wideconv, "INTERPRET", False)
    encoder = (84, (3, 3, 3, 3), 0, (9, 32, 32, 32, 32), True, jnp.uint8, 2, 4 + 4 + 3)
    decoder = (35, (3, 3, 3, 2), (2, 2, 2, 1), (16, 32, 32, 32, 16), False, jnp.bfloat16, 1, 12)
    crops = jax.ShapeDtypeStruct((2, 8, 2), jnp.int32)
    for size, kernels, pads, channels, relu_last, dtype, stride, kernel_count in (
        encoder,
        decoder,
    ):
        x = jax.ShapeDtypeStruct((2, 8, size, size, channels[0]), dtype)
        layers = tuple(
            (
                jax.ShapeDtypeStruct((2, n, n, c, f), jnp.float32),
                jax.ShapeDtypeStruct((2, f), jnp.float32),
            )
            for n, c, f in zip(kernels, channels, channels[1:])
        )

        shift = 4 if stride > 1 else 0

        def loss(x, ws, crops, pads=pads, relu_last=relu_last, stride=stride, shift=shift):
            c = crops if shift else None
            y = wideconv.conv_stack(x, ws, pads, relu_last, jnp.bfloat16, stride, shift, c)
            return jnp.sum(y.astype(jnp.float32))

        argnums = 1 if dtype == jnp.uint8 else (0, 1)
        fn = jax.vmap(jax.value_and_grad(loss, argnums))
        text = jax.jit(fn).trace(x, layers, crops).lower(lowering_platforms=("cuda",)).as_text()
        assert text.count("xla.gpu.triton") == kernel_count
        if stride > 1:  # the frames as given: not edge-padded by the shift, nor converted
            assert "x84x84x9xui8>" in text
            assert "x92x92x9x" not in text
            assert "x84x84x9xbf16>" not in text and "x84x84x9xf32>" not in text
    # the decoder's stack fused with the mask loss: the same kernels, and no XLA op but free
    # reshapes touches the fused kernel's output (the logits' gradient, as its rows)
    labels = jax.ShapeDtypeStruct((2, 8, 84, 84, 3), jnp.uint8)
    crops = jax.ShapeDtypeStruct((2, 8, 2), jnp.int32)

    def bce(x, ws, labels, crops):
        return wideconv.conv_stack_loss(x, ws, labels, pads, jnp.bfloat16, 2, 4, crops)

    fn = jax.jit(jax.vmap(jax.value_and_grad(bce, (0, 1))))
    text = fn.trace(x, layers, labels, crops).lower(lowering_platforms=("cuda",)).as_text()
    assert text.count("xla.gpu.triton") == 12
    rows = wideconv._Grid(8, 42).rows
    touching = [line for line in text.splitlines() if f"x{rows}x16x" in line]
    ops = {re.search(r"stablehlo\.\w+", line).group() for line in touching}
    assert ops == {"stablehlo.custom_call", "stablehlo.reshape"}


def test_networks_with_pallas_stacks_are_the_same_function(monkeypatch):
    """With conv_settings(stack="pallas") the pool encoder and decoder keep their parameters
    (names, shapes, initial values) and give the same values and gradients, the encoder
    reading its pixels through random-shift crops as the XLA path crops them first."""
    monkeypatch.setattr(wideconv, "BLOCK", 1024)  # few programs: the interpreter runs each
    enc, dec = networks.PoolEncoder(64), networks.PoolDecoder(3)
    obs = _pixels(2, (1, 84, 84, 9))
    # offset (1, 7), pad 4: each pixel from 3 rows above and 3 columns right (edges repeat)
    crops = augment.Crops(jnp.array([[1, 7]]), 4, "gather")
    z = _normal(2, (1, 32))

    def init():
        return enc.init(jax.random.key(0), obs), dec.init(jax.random.key(0), z)

    def loss(p, phases):
        latent = enc.apply(p[0], obs, crops)
        decoded = dec.apply(p[1], latent[:, :32], phases=phases)
        return jnp.sum(latent**2) + jnp.sum(jnp.tanh(decoded))

    # Each path jitted on its own (the stack is chosen as the program is traced): one compiled
    # program each, the Pallas kernels compiled once.
    params = jax.jit(init)()
    want = jax.jit(jax.value_and_grad(loss), static_argnums=1)(params, False)
    with networks.conv_settings(stack="pallas"):
        same = jax.jit(init)()
        # the decoder's output as its phases (as the update's losses take it): the same sum
        got = jax.jit(jax.value_and_grad(loss), static_argnums=1)(params, True)
    for a, b in zip(jax.tree.leaves(same), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("channels, loss", [(3, "bce"), (9, "clipped_squares")])
def test_decoder_with_a_target_is_its_loss_on_either_stack(monkeypatch, channels, loss):
    """PoolDecoder(target=(images, crops)) is its loss of its output against the cropped images
    (the mask decoder's BCE against {0, 1} masks, SEAR's reconstruction against uint8 frames);
    with Pallas stacks (the loss fused into the last kernel) the same value and gradients, for
    the parameters and the latent."""
    monkeypatch.setattr(wideconv, "BLOCK", 1024)
    dec = networks.PoolDecoder(channels, loss=loss)
    definition_loss = networks.DECODER_LOSSES[loss]
    z = _normal(2, (2, 32))
    params = jax.jit(dec.init)(jax.random.key(0), z)
    shape = (2, 84, 84, channels)
    images = _bernoulli(3, 0.2, shape).astype(jnp.uint8) if loss == "bce" else _pixels(3, shape)
    crops = augment.Crops(jnp.array([[1, 7], [8, 0]]), 4, "gather")

    def of(p, z):
        return dec.apply(p, z, target=(images, crops))

    def uncropped(p, z):  # two leading axes, images taken as they are
        return dec.apply(p, z, target=(images[None], None))

    # Each path jitted on its own (the stack is chosen as the program is traced).
    definition = jax.jit(lambda p, z: definition_loss(dec.apply(p, z), crops.apply(images)))
    want = jax.jit(jax.value_and_grad(of, (0, 1)))(params, z)
    np.testing.assert_allclose(want[0], definition(params, z), rtol=1e-5)
    with networks.conv_settings(stack="pallas"):
        got = jax.jit(jax.value_and_grad(of, (0, 1)))(params, z)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        scale = float(jnp.abs(b).max())
        np.testing.assert_allclose(a / scale, b / scale, atol=1e-5)
    # the mean over both axes of the loss per image
    per_image = jax.jit(lambda p, z, m: definition_loss(dec.apply(p, z), m))
    one = [per_image(params, z[i : i + 1], images[i : i + 1]) for i in (0, 1)]
    want = jnp.mean(jnp.array(one))
    np.testing.assert_allclose(jax.jit(uncropped)(params, z[None]), want, rtol=1e-5)
    with networks.conv_settings(stack="pallas"):
        np.testing.assert_allclose(jax.jit(uncropped)(params, z[None]), want, rtol=1e-5)
    with pytest.raises(
        ValueError,
        match=rf"target images are \(2, 84, 84, 1\), need \(2, 84, 84, {channels}\)",
    ):
        dec.apply(params, z, target=(images[..., :1], crops))


def test_unknown_stack_is_refused():
    with pytest.raises(ValueError, match="unknown conv stack 'cutlass'"):
        with networks.conv_settings(stack="cutlass"):
            pass
    with pytest.raises(ValueError, match="unknown conv_stack 'cutlass'.*'auto', 'xla', 'pallas'"):
        update.AgentConfig(action_dim=6, conv_stack="cutlass")


def test_auto_stack_is_pallas_on_gpus_only(monkeypatch):
    assert networks.stack_for("xla") == "xla" and networks.stack_for("pallas") == "pallas"
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
    assert networks.stack_for("auto") == "xla"
    with networks.conv_settings(stack="auto"):
        assert networks._CONV.get().stack == "xla"
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert networks.stack_for("auto") == "pallas"
    with networks.conv_settings(stack="auto"):
        assert networks._CONV.get().stack == "pallas"
