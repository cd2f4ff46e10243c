"""A roofline of one seed-update of any method (pool encoder): FLOPs and minimal bytes per layer
and pass, the floor they imply on an H100 SXM, and XLA's own FLOP count to check them.

python -m benchmarks.roofline [--method dear] [--batch 512] [--dtype bfloat16] [--out FILE]
    [--no-xla]

Nothing is timed: every figure is computed from the layer shapes, which are read from the real
parameters (`jax.eval_shape` of `update.init_params`), so they follow any change of width. One
seed-update at batch B does (`update.update`):
  * encoder on obs (forward and backward) and on next_obs (forward only: its latent is stopped);
    TED also on an observation of the same episode (forward only);
  * critic on (z, action), forward and backward (input gradients to z, weight gradients);
  * DEAR and SEAR: the mask decoder on z_agent, forward and backward, and the mask loss; DEAR:
    the orthogonality loss; SEAR: the reconstruction decoder on z_env, forward and backward, and
    its loss; TED: its classifier on three pairs of latents per sample;
  * target critic and actor on z_next, forward only (the TD target);
  * actor step: actor and the updated critic on the stopped z, forward; backward through the
    critic's Q heads to the action (input gradients only) and through the actor (weight
    gradients, input gradients down to its trunk's output);
  * Adam on the learner's and the actor's parameters, the target critic's EMA.

Counting:
  * FLOPs: those of the matrix products and convolutions only, a multiply-add counted as 2.
    Convolutions are counted as the code computes them: a transposed convolution as the dense
    convolution of its output phases (`networks.ConvTranspose`; the decoder's last layer has 16
    taps per output pixel group where 9 are non-zero), without the channel padding of the
    tensor-core and Pallas paths. Backward = input gradient + weight gradient, each as many
    FLOPs as the forward product (the first conv layer has no input gradient: the pixels are
    not differentiated). Elementwise work (bias, ReLU, LayerNorm, tanh, pooling, losses, Adam)
    is not counted as FLOPs: it is memory-bound at these sizes and its bytes are counted.
  * Bytes: each layer reads its inputs and weights once and writes its outputs once, unfused
    layer by layer (bias and activation, and their gradients, fused into the layer). Encoder
    and decoder activations and their gradients are bf16 (float32 with --dtype float32); the
    frames are uint8; the latent z, the actor's and critic's activations and gradients are
    float32, as the code keeps them. Weights are read as stored (float32: the cast to the
    compute dtype is fused into the read) and weight gradients written as float32. The mask
    loss and its gradient are one elementwise pass: read the logits and the uint8 masks, write
    the logits' gradient; SEAR's reconstruction loss likewise, with the uint8 frames. TED's
    classifier is elementwise on float32 latents (no FLOPs counted). Adam reads parameter,
    gradient and both moments and writes parameter and moments (7 float32 accesses per
    parameter); the EMA reads two and writes one.
  * Compute peaks: bf16 products on tensor cores; float32 products (the actor's and critic's
    gradients, every product with --dtype float32) in TF32 on tensor cores, as XLA runs float32
    products on GPUs by default.

Floor of a layer = max(FLOPs / peak, bytes / bandwidth); the floor of the update is the sum over
layers (a lower bound only if layers run one after another at best each alone; no overlap of
layers is assumed). Prints Markdown tables and writes JSON (`common.save_json`).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math

import jax
import jax.numpy as jnp

from benchmarks.common import save_json
from dear_jax import networks, update

# NVIDIA H100 SXM5 80GB, NVIDIA's H100 Tensor Core GPU datasheet
# (https://www.nvidia.com/en-us/data-center/h100/): "BF16 Tensor Core 1,979 teraFLOPS*",
# "TF32 Tensor Core 989 teraFLOPS*" (* with sparsity; dense figures are one half), "FP32 67
# teraFLOPS", "GPU memory bandwidth 3.35TB/s". The dense peaks below are those halves.
H100_SXM = dict(
    name="NVIDIA H100 SXM5 80GB (datasheet peaks, dense)",
    source="NVIDIA H100 Tensor Core GPU datasheet, H100 SXM column; tensor-core figures halved "
    "(the datasheet's are with 2:4 sparsity)",
    peak_flops={"bf16": 989.4e12, "tf32": 494.7e12, "fp32": 66.9e12},
    bandwidth=3.35e12,
)


@dataclasses.dataclass(frozen=True)
class Layer:
    part: str  # network part (table group)
    row: str  # table row within the part
    name: str  # the layer
    phase: str  # "forward" or "backward"
    flops: float
    bytes: float
    compute: str  # peak it runs at: "bf16", "tf32" or "none" (elementwise, no FLOPs counted)


def passes(part, row, name, n_fwd, n_bwd, cost, fwd, bwd, *, dx=True, dw=True) -> list[Layer]:
    """A layer's forward row over n_fwd items and backward row over n_bwd items from its
    per-item `cost` (flops, x bytes, y bytes) and weight bytes (cost["w"]).

    Forward: read x and W, write y. Input gradient: read dy and W, write dx. Weight gradient:
    read x and dy, write dW. Each product costs the forward's FLOPs."""
    f, x, y, w = cost["flops"], cost["x"], cost["y"], cost["w"]
    rows = [Layer(part, row, name, "forward", n_fwd * f, n_fwd * (x + y) + w, fwd)]
    grads = int(dx) + int(dw)
    if n_bwd and grads:
        rows.append(
            Layer(
                part, row, name, "backward", grads * n_bwd * f, grads * (n_bwd * (x + y) + w), bwd
            )
        )
    return rows


def dense_cost(din: int, dout: int, in_b: int, out_b: int) -> dict:
    """Per-item FLOPs and bytes of a Linear layer din -> dout (float32 weights and bias)."""
    return dict(flops=2 * din * dout, x=din * in_b, y=dout * out_b, w=(din * dout + dout) * 4)


def conv_cost(side_in, cin, cout, k, stride, in_b, out_b, *, calc=None, params=None) -> dict:
    """Per-image FLOPs and bytes of a VALID k x k convolution of a [side_in, side_in, cin] image
    with `stride`, to [side_out, side_out, cout] (float32 kernel and bias).

    `calc` = (output side, input channels, output channels, taps) of the product as computed,
    where it differs (a transposed convolution's output phases); `params`: the stored kernel and
    bias size, where the computed kernel differs from it."""
    side_out = (side_in - k) // stride + 1
    side_c, cin_c, cout_c, k_c = calc or (side_out, cin, cout, k)
    weights = params if params is not None else k * k * cin * cout + cout
    return dict(
        flops=2 * side_c**2 * k_c**2 * cin_c * cout_c,
        x=side_in**2 * cin * in_b,
        y=side_out**2 * cout * out_b,
        w=weights * 4,
        side_out=side_out,
    )


def _size(tree) -> int:
    return sum(math.prod(x.shape) for x in jax.tree.leaves(tree))


def param_shapes(cfg: update.AgentConfig) -> dict:
    return jax.eval_shape(functools.partial(update.init_params, cfg), jax.random.key(0))


def _heads(part, params, n, fwd, bwd, *, trunk_dx, dw, mlp_dx) -> list[Layer]:
    """An actor or a critic (trunk Linear + LayerNorm + tanh, then one or two MLPs), all
    float32 activations; backward rows only where gradients are asked for."""
    f32 = 4
    d_in, d_out = params["Trunk_0"]["Dense_0"]["kernel"].shape
    rows = passes(
        part,
        part,
        "Trunk Dense",
        n,
        n,
        dense_cost(d_in, d_out, f32, f32),
        fwd,
        bwd,
        dx=trunk_dx,
        dw=dw,
    )
    ln = n * d_out * f32
    rows.append(Layer(part, part, "LayerNorm+tanh", "forward", 0, 2 * ln, "none"))
    if dw:  # read the trunk's output and its gradient, write the input gradient
        rows.append(Layer(part, part, "LayerNorm+tanh", "backward", 0, 3 * ln, "none"))
    mlps = [params[h] for h in ("q1", "q2")] if "q1" in params else [params["MLP_0"]]
    for m, mlp in enumerate(mlps):
        for j in range(len(mlp)):
            d_in, d_out = mlp[f"Dense_{j}"]["kernel"].shape
            cost = dense_cost(d_in, d_out, f32, f32)
            rows += passes(part, part, f"MLP {m} Dense {j}", n, n, cost, fwd, bwd, dx=mlp_dx, dw=dw)
    return rows


# ms per seed-update measured for each method: 5 seeds, batch 512, bf16, Pallas stacks, H100
# (commit 4bc20e4, benchmarks/results/methods/update_methods_pallas_taploop_h100.json).
MEASURED_MS = {"dear": 2.62, "drqv2": 1.64, "sear": 3.81, "ted": 2.00}


def _decoder(part: str, dec: dict, B: int, a: int, conv: str, loss: str) -> list[Layer]:
    """A PoolDecoder on half the latent (float32), forward and backward, and its loss as one
    elementwise pass: read the output and the uint8 targets, write the output's gradient."""
    f32 = 4
    out: list[Layer] = []
    half, hidden = dec["Dense_0"]["kernel"].shape
    row = f"Dense ({half}->{hidden})"
    out += passes(part, row, row, B, B, dense_cost(half, hidden, f32, a), conv, conv)
    names = sorted((k for k in dec if k.startswith("ConvTranspose_")), key=lambda s: int(s[14:]))
    side = math.isqrt(hidden // dec[names[0]]["kernel"].shape[2])
    for i, name in enumerate(names):
        kh, _, cin, cout = dec[name]["kernel"].shape
        s, op = (
            (4, 3) if i == 0 else (networks.DECODER_STRIDE, 1) if i == len(names) - 1 else (1, 0)
        )
        taps, size, per_phase = networks._subpixel_geometry(side, kh, s, op)
        # As computed: a VALID taps x taps convolution of the input padded to per_phase + taps - 1
        # with s*s*cout output channels, on per_phase^2 pixels; bytes of the true input and output.
        cost = conv_cost(
            side,
            cin,
            cout,
            1,
            1,
            a,
            a,
            calc=(per_phase, cin, s * s * cout, taps),
            params=kh * kh * cin * cout + cout,
        )
        cost["y"] = size * size * cout * a
        row = f"ConvT {i + 1} ({side}->{size}, {cin}->{cout}, k{kh} s{s})"
        out += passes(part, row, row, B, B, cost, conv, conv)
        side = size
    out.append(Layer(part, loss, loss, "backward", 0, B * side * side * cout * (a + 1 + a), "none"))
    return out


def layers(cfg: update.AgentConfig, batch: int) -> list[Layer]:
    """Every layer of one seed-update of cfg.method at `batch`, forward and backward."""
    if cfg.encoder != "pool":
        raise ValueError("the roofline models the pool encoder's update only")
    p = param_shapes(cfg)
    bf16 = cfg.compute_dtype == "bfloat16"
    a = 2 if bf16 else 4  # encoder / decoder activations and their gradients
    conv = "bf16" if bf16 else "tf32"  # convolutions, encoder and decoder Linear layers
    head_fwd = conv  # actor and critic forward products (bf16 operands in the bf16 path)
    head_bwd = "tf32"  # their gradients' products: float32 cotangents
    B, f32 = batch, 4
    out: list[Layer] = []

    # Encoder: on obs (forward, backward) and next_obs (forward only: its latent is stopped), and
    # for TED on a frame of the same episode (forward only).
    n_fwd = (3 if cfg.method == "ted" else 2) * B
    enc = p["encoder"]
    trunk = enc["ConvTrunk_0"]
    side, in_b = cfg.obs_shape[0], 1  # uint8 frames, read through the random shift's crops
    for i in range(len(trunk)):
        k, _, cin, cout = trunk[f"Conv_{i}"]["kernel"].shape
        stride = 2 if i == 0 else 1
        cost = conv_cost(side, cin, cout, k, stride, in_b, a)
        row = f"conv {i + 1} ({side}->{cost['side_out']}, {cin}->{cout}, s{stride})"
        # the first layer has no input gradient: the pixels are not differentiated
        out += passes("encoder", row, row, n_fwd, B, cost, conv, conv, dx=i > 0)
        side, in_b = cost["side_out"], a
    pooled = side // 4
    pool = dict(flops=0, x=side * side * cout * a, y=pooled * pooled * cout * a, w=0)
    out += passes("encoder", "avg pool 4x4", "avg pool", n_fwd, B, pool, "none", "none", dw=False)
    din, latent = enc["Dense_0"]["kernel"].shape
    assert din == pooled * pooled * cout, (din, pooled, cout)
    row = f"Dense ({din}->{latent})"
    out += passes("encoder", row, row, n_fwd, B, dense_cost(din, latent, a, f32), conv, conv)

    # Critic (learner step): forward and backward, gradients to z and to its weights.
    crit = p["critic"]
    out += _heads("critic", crit, B, head_fwd, head_bwd, trunk_dx=True, dw=True, mlp_dx=True)

    if cfg.uses_mask:  # DEAR, SEAR: the mask decoder on z_agent
        out += _decoder("mask decoder", p["mask_decoder"], B, a, conv, "mask loss")
    if cfg.method == "sear":  # the reconstruction decoder on z_env, against the 9-channel frames
        out += _decoder("recon decoder", p["recon_decoder"], B, a, conv, "reconstruction loss")
    if cfg.method == "dear":  # orthogonality loss: read z; its gradient: read z, write dz
        out += [
            Layer(
                "losses", "orthogonality", "orthogonality", "forward", 0, B * latent * f32, "none"
            ),
            Layer(
                "losses",
                "orthogonality",
                "orthogonality",
                "backward",
                0,
                2 * B * latent * f32,
                "none",
            ),
        ]
    if cfg.method == "ted":  # three pairs per sample: read both latents; backward to z_t only
        pairs = 3 * B * 2 * latent * f32
        out += [
            Layer("losses", "TED classifier", "TED classifier", "forward", 0, pairs, "none"),
            Layer("losses", "TED classifier", "TED classifier", "backward", 0, 2 * pairs, "none"),
        ]

    # TD target: actor and target critic on z_next, forward only.
    none = dict(trunk_dx=False, dw=False, mlp_dx=False)
    out += _heads("target critic", crit, B, head_fwd, head_bwd, **none)
    out += _heads("actor (next action)", p["actor"], B, head_fwd, head_bwd, **none)
    # Actor step on the stopped z: the actor's weight gradients (input gradients down to its
    # trunk's output); the updated critic forward, its Q heads' input gradients to the action.
    out += _heads("actor", p["actor"], B, head_fwd, head_bwd, trunk_dx=False, dw=True, mlp_dx=True)
    out += _heads(
        "critic (actor step)", crit, B, head_fwd, head_bwd, trunk_dx=False, dw=False, mlp_dx=True
    )

    # Adam on the learner (encoder, critic, decoder) and the actor; the target critic's EMA.
    learner = _size({k: v for k, v in p.items() if k != "actor"})
    opt = "Adam + target EMA"
    out += [
        Layer("optimizer", opt, "Adam (learner)", "backward", 0, 7 * f32 * learner, "none"),
        Layer("optimizer", opt, "Adam (actor)", "backward", 0, 7 * f32 * _size(p["actor"]), "none"),
        Layer("optimizer", opt, "target EMA", "backward", 0, 3 * f32 * _size(crit), "none"),
    ]
    return out


def floor_s(layer: Layer, hw=H100_SXM) -> tuple[float, float]:
    """(compute time, memory time) of a layer at the hardware's peaks."""
    compute = layer.flops / hw["peak_flops"][layer.compute] if layer.flops else 0.0
    return compute, layer.bytes / hw["bandwidth"]


def summarize(rows: list[Layer], hw=H100_SXM) -> dict:
    """Per-layer floors, per (part, row, pass) and per part sums, and the total."""
    detail = []
    for r in rows:
        c, m = floor_s(r, hw)
        detail.append(
            {
                **dataclasses.asdict(r),
                "compute_us": c * 1e6,
                "memory_us": m * 1e6,
                "floor_us": max(c, m) * 1e6,
                "bound": "compute" if c > m else "memory",
            }
        )

    def group(keys):
        out = {}
        for d in detail:
            g = out.setdefault(
                tuple(d[k] for k in keys), dict(flops=0, bytes=0, floor_us=0, compute_bound_us=0)
            )
            g["flops"] += d["flops"]
            g["bytes"] += d["bytes"]
            g["floor_us"] += d["floor_us"]
            g["compute_bound_us"] += d["floor_us"] if d["bound"] == "compute" else 0
        for g in out.values():
            share = g.pop("compute_bound_us") / g["floor_us"] if g["floor_us"] else 0
            g["bound"] = "compute" if share > 0.9 else "memory" if share < 0.1 else "mixed"
        return out

    rows_ = [
        dict(zip(("part", "row", "phase"), k), **v)
        for k, v in group(("part", "row", "phase")).items()
    ]
    parts = [dict(part=k[0], **v) for k, v in group(("part",)).items()]
    total = {k: sum(p[k] for p in parts) for k in ("flops", "bytes", "floor_us")}
    return dict(layers=detail, rows=rows_, parts=parts, total=total)


def xla_cost(cfg: update.AgentConfig, batch: int) -> dict:
    """XLA's cost analysis of the compiled seed-update on this backend (meant for CPU, with
    conv_stack "xla": no Pallas kernels, whose cost XLA does not see)."""
    from benchmarks.update import random_batch

    key = jax.random.key(0)
    state = jax.eval_shape(functools.partial(update.init, cfg), key)
    data = jax.eval_shape(
        lambda k: random_batch(k, batch, cfg.action_dim, cfg.method == "ted"), key
    )
    hp = jax.tree.map(jnp.float32, update.HParams())
    step = jax.jit(functools.partial(update.update, cfg=cfg))
    cost = step.lower(state, data, key, hp).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, list | tuple) else cost
    return {k: float(cost[k]) for k in ("flops", "transcendentals", "bytes accessed") if k in cost}


def _fmt_flops(x):
    return f"{x / 1e9:.2f} G"


def _fmt_bytes(x):
    return f"{x / 1e6:.1f} MB"


def markdown(summary: dict) -> str:
    lines = [
        "| part | layer | pass | FLOPs | bytes | bound | floor µs |",
        "|---|---|---|---:|---:|---|---:|",
    ]
    for r in summary["rows"]:
        lines.append(
            f"| {r['part']} | {r['row']} | {r['phase']} | {_fmt_flops(r['flops'])} | "
            f"{_fmt_bytes(r['bytes'])} | {r['bound']} | {r['floor_us']:.1f} |"
        )
    lines += [
        "",
        "| part | FLOPs | bytes | bound | floor µs | share |",
        "|---|---:|---:|---|---:|---:|",
    ]
    t = summary["total"]
    for r in summary["parts"]:
        lines.append(
            f"| {r['part']} | {_fmt_flops(r['flops'])} | {_fmt_bytes(r['bytes'])} | {r['bound']} "
            f"| {r['floor_us']:.1f} | {r['floor_us'] / t['floor_us']:.0%} |"
        )
    lines.append(
        f"| **total** | {_fmt_flops(t['flops'])} | {_fmt_bytes(t['bytes'])} | | "
        f"**{t['floor_us']:.1f}** | |"
    )
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--method", default="dear", choices=update.METHODS)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--dtype", default="bfloat16", choices=["float32", "bfloat16"])
    parser.add_argument("--action-dim", type=int, default=6)
    parser.add_argument("--no-xla", action="store_true", help="skip XLA's cost analysis")
    parser.add_argument(
        "--measured-ms",
        type=float,
        default=None,
        help="measured ms per seed-update to set against the floor (default: MEASURED_MS, the "
        "method at 5 seeds, batch 512, bf16, Pallas stacks, on an H100)",
    )
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    if args.measured_ms is None:
        args.measured_ms = MEASURED_MS[args.method]
    cfg = update.AgentConfig(
        action_dim=args.action_dim, method=args.method, compute_dtype=args.dtype, conv_stack="xla"
    )
    layers_ = layers(cfg, args.batch)
    summary = summarize(layers_)
    print(f"{args.method} seed-update, batch {args.batch}, {args.dtype}; {H100_SXM['name']}")
    print(markdown(summary))
    t = summary["total"]
    result = dict(
        method=args.method,
        batch=args.batch,
        dtype=args.dtype,
        hardware=H100_SXM,
        **summary,
    )
    hw = H100_SXM
    compute_us = sum(x.flops / hw["peak_flops"][x.compute] for x in layers_ if x.flops) * 1e6
    result["total"].update(
        compute_only_us=compute_us,
        memory_only_us=t["bytes"] / hw["bandwidth"] * 1e6,
        measured_ms=args.measured_ms,
        measured_over_floor=args.measured_ms * 1e3 / t["floor_us"],
    )
    print(
        f"floor {t['floor_us']:.0f} µs per seed-update (FLOPs alone {compute_us:.0f} µs, bytes "
        f"alone {t['bytes'] / hw['bandwidth'] * 1e6:.0f} µs); measured {args.measured_ms} ms = "
        f"{args.measured_ms * 1e3 / t['floor_us']:.2f}x the floor"
    )
    if not args.no_xla:
        xla = xla_cost(cfg, args.batch)
        result["xla_cost_analysis"] = dict(backend=jax.default_backend(), **xla)
        print(
            f"XLA cost analysis ({jax.default_backend()}, conv_stack xla): "
            f"{xla['flops'] / 1e9:.2f} GFLOP against {t['flops'] / 1e9:.2f} GFLOP counted here "
            f"({xla['flops'] / t['flops']:.3f}x); "
            f"bytes accessed {xla.get('bytes accessed', 0) / 1e6:.0f} MB"
        )
    save_json(result, args.out, f"benchmarks/results/roofline/roofline_{args.method}.json")


if __name__ == "__main__":
    main()
