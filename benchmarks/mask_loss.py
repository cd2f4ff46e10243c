"""The mask decoder with its loss, as the DEAR update runs it: the loss fused into the decoder's
last Pallas kernel against the logits written out and the loss taken by XLA.

    python -m benchmarks.mask_loss [--seeds 5] [--batch 512] [--iters 20] [--out FILE]

Each variant is the loss and its gradients (decoder parameters and latent) of a batch per seed,
vmapped over the seeds, in bf16, with random-shift crops of the masks:
- fused: `PoolDecoder(target=(mask, crops))` on Pallas stacks (`wideconv.conv_stack_bce`);
- logits_pallas: the decoder's logits from Pallas stacks, then `losses.mask_loss` against the
  cropped masks laid out as the logits' phases (the update before the fused loss);
- logits_xla: the same on XLA's convolutions.
Prints ms per call and per seed, and each variant's largest difference from the same loss in
float32 on XLA's convolutions (the loss relative to its value; each gradient array relative to
its norm, the largest of them); writes JSON (default benchmarks/results/mask_loss_<platform>.json).
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp

from benchmarks.common import save_json, timed_calls
from dear_jax import augment, losses, networks

HALF_LATENT = 2048  # z_agent: half of DEAR's 4096-wide latent


def loss_fn(dtype: str, fused: bool):
    """(decoder params, z_agent [B, F], masks [B, 84, 84, 3], crop offsets [B, 2]) -> loss."""
    dec = networks.PoolDecoder(3, jnp.dtype(dtype))

    def loss(params, z, mask, offsets):
        crops = augment.Crops(offsets, augment.DEFAULT_PAD, "gather")
        if fused:
            return dec.apply(params, z, target=(mask, crops))
        logits = dec.apply(params, z, phases=True)
        return losses.mask_loss(logits, networks.decoder_phases(crops.apply(mask)))

    return loss


VARIANTS = {  # name: (conv stack, fused)
    "fused": ("pallas", True),
    "logits_pallas": ("pallas", False),
    "logits_xla": ("xla", False),
}


def inputs(seeds: int, batch: int):
    kp, kz, km, kc = jax.random.split(jax.random.key(0), 4)
    z = jax.random.normal(kz, (seeds, batch, HALF_LATENT))
    init = networks.PoolDecoder(3).init
    params = jax.vmap(init)(jax.random.split(kp, seeds), z[:, :1])
    mask = jax.random.bernoulli(km, 0.15, (seeds, batch, 84, 84, 3)).astype(jnp.uint8)
    offsets = jax.random.randint(kc, (seeds, batch, 2), 0, 2 * augment.DEFAULT_PAD + 1)
    return params, z, mask, offsets


def largest_differences(got, want) -> tuple[float, float]:
    """(the loss's relative difference, the largest over gradient arrays of ||got - want|| over
    ||want|| (L2 norms))."""
    (loss, grads), (ref_loss, ref_grads) = got, want
    rel = float(jnp.max(jnp.abs(loss - ref_loss) / jnp.abs(ref_loss)))
    grad = max(
        float(jnp.linalg.norm(a.astype(jnp.float32) - b) / jnp.linalg.norm(b))
        for a, b in zip(jax.tree.leaves(grads), jax.tree.leaves(ref_grads), strict=True)
    )
    return rel, grad


def run(seeds: int, batch: int, iters: int, names=tuple(VARIANTS)) -> list[dict]:
    args = inputs(seeds, batch)

    def program(stack, dtype, fused):
        fn = jax.jit(jax.vmap(jax.value_and_grad(loss_fn(dtype, fused), (0, 1))))
        with networks.conv_settings(stack=stack):  # traced, so compiled, in this setting
            out = jax.block_until_ready(fn(*args))
        return fn, out

    _, reference = program("xla", "float32", False)
    rows = []
    for name in names:
        stack, fused = VARIANTS[name]
        fn, out = program(stack, "bfloat16", fused)
        ms, dispatch = timed_calls(lambda i, fn=fn: fn(*args), iters)
        loss_diff, grad_diff = largest_differences(out, reference)
        rows.append(
            dict(
                variant=name,
                conv_stack=stack,
                dtype="bfloat16",
                seeds=seeds,
                batch=batch,
                ms_per_call=ms,
                ms_per_seed=ms / seeds,
                dispatch_ms_per_call=dispatch,
                loss_rel_diff_vs_f32=loss_diff,
                grad_max_rel_diff_vs_f32=grad_diff,
            )
        )
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--iters", type=int, default=20)
    p.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    p.add_argument("--out")
    a = p.parse_args(argv)
    rows = run(a.seeds, a.batch, a.iters, a.variants)
    print(
        "| variant | conv stack | seeds | batch | ms per call | ms per seed "
        "| loss vs f32 | gradients vs f32 |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['variant']} | {r['conv_stack']} | {r['seeds']} | {r['batch']} "
            f"| {r['ms_per_call']:.3f} | {r['ms_per_seed']:.3f} "
            f"| {r['loss_rel_diff_vs_f32']:.1e} | {r['grad_max_rel_diff_vs_f32']:.1e} |"
        )
    result = dict(device=jax.devices()[0].device_kind, jax=jax.__version__, rows=rows)
    save_json(result, a.out, f"benchmarks/results/mask_loss_{jax.default_backend()}.json")
    return rows


if __name__ == "__main__":
    main()
