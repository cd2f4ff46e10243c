"""Time the jitted, seed-vmapped learner update (encoder + heads + critic, actor, target EMA).

python -m benchmarks.update [--methods dear drqv2] [--seeds 1 5] [--batch 256] [--iters 20]
    [--dtypes float32 bfloat16] [--seed-axis vmap loop]
    [--conv-stacks pallas --kernels default TAP_LOOP=1,CONV_STAGES=2] [--keys fresh fixed]
    [--xla-options "" xla_gpu_command_buffer_scheduling_mode=CONCURRENT]
Prints a table and writes JSON to benchmarks/results/update_<platform>.json (or --out).
--kernels (with --conv-stacks pallas) times each listed setting of the Pallas conv stacks'
constants (`dear_jax.wideconv`, comma-separated NAME=INT; "default": as they are), in turn, for
every other combination. --keys: each call's key a new array (fresh, as in training) or one array
for every call (fixed: no argument moves between calls). Each row records a digest of the states
its calls leave (`state_digest`): flags that change no arithmetic leave it as it was.
--xla-options: the update program's XLA options, each setting in turn (default: a run's
agent.xla_options default; "": XLA's own).
The same update in PyTorch, timed on the same GPU: `python -m benchmarks.torch_reference update`.
"""

from __future__ import annotations

import argparse
import functools
import itertools
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import save_json, timed_calls
from configs import base
from dear_jax import augment, experiment, networks, update, wgrad, wideconv
from dear_jax.replay import Batch

# docs/design.md: the PyTorch reference architecture's DEAR update, batch 256, TF32, on an H100.
PYTORCH_ANCHOR_MS = 12.1
KEYS = ("fresh", "fixed")  # time_update's keys


def random_batch(key, batch, action_dim, far):
    k = jax.random.split(key, 5)
    img = lambda kk: jax.random.randint(kk, (batch, 84, 84, 9), 0, 256).astype(jnp.uint8)  # noqa: E731
    return Batch(
        obs=img(k[0]),
        action=jax.random.uniform(k[1], (batch, action_dim), minval=-1, maxval=1),
        reward=jax.random.uniform(k[2], (batch,)),
        discount=jnp.full((batch,), 0.99),
        next_obs=img(k[3]),
        mask=(jax.random.uniform(k[4], (batch, 84, 84, 3)) > 0.8).astype(jnp.uint8),
        far_obs=img(k[0]) if far else None,
        far_valid=jnp.ones(batch) if far else None,
    )


def update_setup(
    method,
    seeds,
    batch,
    dtype="float32",
    seed_axis="vmap",
    action_dim=6,
    shift_impl="gather",
    encoder="pool",
    filter_gradient="cudnn",
    conv_stack="xla",
    kernels="",
    xla_options="",
):
    """(jitted update over all seeds, fresh agent states, random batches, hparams); `kernels`:
    the Pallas stacks' constants, as a run's agent.kernels sets them; `xla_options`: XLA's, as
    agent.xla_options."""
    cfg = update.AgentConfig(
        action_dim=action_dim,
        method=method,
        compute_dtype=dtype,
        shift_impl=shift_impl,
        encoder=encoder,
        filter_gradient=filter_gradient,
        conv_stack=conv_stack,
        kernels=kernels,
    )
    states = jax.jit(functools.partial(update.init_seeds, cfg))(
        jax.random.split(jax.random.key(0), seeds)
    )
    batches = jax.vmap(lambda k: random_batch(k, batch, action_dim, method == "ted"))(
        jax.random.split(jax.random.key(1), seeds)
    )
    hp = update.HParams().for_seeds(seeds)
    step = jax.jit(
        update.over_seeds(functools.partial(update.update, cfg=cfg), seed_axis),
        donate_argnums=0,
        compiler_options=experiment.xla_options(xla_options),
    )
    return step, states, batches, hp


def time_update(
    method: str,
    seeds: int,
    batch: int,
    iters: int,
    dtype: str = "float32",
    action_dim: int = 6,
    seed_axis: str = "vmap",
    shift_impl: str = "gather",
    encoder: str = "pool",
    filter_gradient: str = "cudnn",
    conv_stack: str = "xla",
    kernels: str = "",
    keys: str = "fresh",
    xla_options: str = "",
) -> dict:
    """Milliseconds per call, and the host's dispatch per call (`common.timed_calls`). `keys`:
    "fresh", a new key array each call, as the training loop gives; "fixed", the same array every
    call, so that no argument of a call lies elsewhere than the last call's (the donated states
    come back in place): XLA updates a recorded command buffer only for allocations that moved."""
    step, states, batches, hp = update_setup(
        method,
        seeds,
        batch,
        dtype,
        seed_axis,
        action_dim,
        shift_impl,
        encoder,
        filter_gradient,
        conv_stack,
        kernels,
        xla_options,
    )
    if keys not in KEYS:
        raise ValueError(f"keys {keys!r}: one of {KEYS}")
    # One array per call, cut before the timing: the calls dispatch nothing else.
    split = jax.random.split(jax.random.key(2), (iters + 1, seeds))
    mode = keys
    keys = [split[0]] * (iters + 1) if mode == "fixed" else list(split)
    t0 = time.perf_counter()
    states, metrics = step(states, batches, keys[0], hp)
    jax.block_until_ready(metrics)
    compile_s = time.perf_counter() - t0

    def call(i):
        nonlocal states
        states, metrics = step(states, batches, keys[i + 1], hp)
        return metrics

    ms, dispatch = timed_calls(call, iters)
    return dict(
        # The same calls from the same inputs: settings that compute the same numbers (flags
        # of the runtime, not of the arithmetic) leave the same digest.
        digest=state_digest(states),
        dtype=dtype,
        precision=str(jax.config.jax_default_matmul_precision),
        method=method,
        encoder=encoder,
        filter_gradient=filter_gradient,
        conv_stack=conv_stack,
        # the Pallas kernel's choices, where it ran
        wgrad=dict(images=wgrad.IMAGES, num_warps=wgrad.NUM_WARPS)
        if filter_gradient == "pallas"
        else None,
        seed_axis=seed_axis,
        shift_impl=shift_impl,
        seeds=seeds,
        batch=batch,
        keys=mode,
        xla_options=xla_options,
        ms_per_call=ms,
        ms_per_seed_update=ms / seeds,
        dispatch_ms_per_call=dispatch,
        compile_s=compile_s,
    )


def state_digest(tree) -> float:
    """The sum of every float leaf of `tree` in float64, on the host: a fingerprint of values."""
    leaves = [
        np.asarray(x, np.float64)
        for x in jax.tree.leaves(tree)
        if jnp.issubdtype(x.dtype, jnp.floating)
    ]
    return float(sum(x.sum() for x in leaves))


def kernel_setting(text: str) -> dict:
    """ "NAME=INT,..." (wideconv.TUNABLE) or "default" -> {NAME: INT}."""
    try:
        return {} if text == "default" else wideconv.parse_constants(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--methods", nargs="+", default=["dear"], choices=update.METHODS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 5])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--seed-axis", nargs="+", default=["vmap"], choices=update.SEED_AXES)
    parser.add_argument("--dtypes", nargs="+", default=["float32"], choices=["float32", "bfloat16"])
    parser.add_argument(
        "--drqv2-encoder",
        default="pool",
        choices=["pool", "plain"],
        help="DrQ-v2's encoder (plain: DrQ-v2's own, as in configs/walker_drqv2_paper.py)",
    )
    parser.add_argument(
        "--filter-gradients", nargs="+", default=["cudnn"], choices=networks.FILTER_GRADIENTS
    )
    parser.add_argument(
        "--conv-stacks",
        nargs="+",
        default=["xla"],
        choices=networks.STACKS,
        help="how the stride-1 conv layers run (agent.conv_stack)",
    )
    parser.add_argument("--shift-impls", nargs="+", default=["gather"], choices=augment.SHIFT_IMPLS)
    parser.add_argument(
        "--precision",
        default=None,
        choices=["default", "tensorfloat32", "float32", "highest"],
        help="jax_default_matmul_precision for float32 matmuls and convolutions",
    )
    parser.add_argument("--kernels", nargs="+", default=[{}], type=kernel_setting)
    parser.add_argument(
        "--keys",
        nargs="+",
        default=["fresh"],
        choices=KEYS,
        help="each call's key: a new array (fresh) or the same one (fixed: no argument moves)",
    )
    parser.add_argument(
        "--xla-options",
        nargs="+",
        default=[base.get_config().agent.xla_options],
        help='the update program\'s XLA options, as agent.xla_options (default its default; "": '
        "XLA's own)",
    )
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    if any(args.kernels) and "pallas" not in args.conv_stacks:
        parser.error("--kernels sets the Pallas stacks' constants: give --conv-stacks pallas")
    if args.precision:
        jax.config.update("jax_default_matmul_precision", args.precision)
    device = jax.devices()[0]
    rows = []
    for d in args.dtypes:
        for m in args.methods:
            for s in args.seeds:
                for how, impl, fg, cs, kernels, keys, xo in itertools.product(
                    args.seed_axis,  # one seed too: "loop" is then the update without vmap
                    args.shift_impls,
                    args.filter_gradients,
                    args.conv_stacks,
                    args.kernels,
                    args.keys,
                    args.xla_options,
                ):
                    encoder = args.drqv2_encoder if m == "drqv2" else "pool"
                    setting = ",".join(f"{n}={v}" for n, v in kernels.items())
                    r = time_update(
                        m,
                        s,
                        args.batch,
                        args.iters,
                        d,
                        6,
                        how,
                        impl,
                        encoder,
                        fg,
                        cs,
                        setting,
                        keys,
                        xo,
                    )
                    rows.append(dict(r, kernels=kernels))
                    print(
                        f"{m} {d} {how} {impl} {fg} {cs} {kernels or ''} {keys} keys {xo!r}, "
                        f"seeds={s}: "
                        f"{r['ms_per_seed_update']:.2f} ms/seed"
                    )
    print(f"device: {device.device_kind} ({device.platform}), jax {jax.__version__}")
    print(
        "| method | encoder | dtype | precision | seed axis | shift | filter gradient | conv stack | kernels | keys | seeds | batch | ms per call "
        "| host dispatch ms per call | ms per seed-update | vs PyTorch 12.1 ms | compile s | digest |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['method']} | {r['encoder']} | {r['dtype']} | {r['precision']} | {r['seed_axis']} "
            f"| {r['shift_impl']} | {r['filter_gradient']} | {r['conv_stack']} "
            f"| {','.join(f'{n}={v}' for n, v in r['kernels'].items()) or 'default'} "
            f"| {r['keys']} | {r['seeds']} | {r['batch']} | "
            f"{r['ms_per_call']:.2f} | {r['dispatch_ms_per_call']:.2f} | "
            f"{r['ms_per_seed_update']:.2f} | {PYTORCH_ANCHOR_MS / r['ms_per_seed_update']:.2f}x "
            f"| {r['compile_s']:.1f} | {r['digest']:.10g} |"
        )
    save_json(
        dict(device=device.device_kind, jax=jax.__version__, rows=rows),
        args.out,
        f"benchmarks/results/update_{device.platform}.json",
    )


if __name__ == "__main__":
    main()
