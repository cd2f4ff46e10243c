"""The stride-1 conv stacks of a DEAR update: cuDNN layer by layer against dear_jax.wideconv.

    python -m benchmarks.wideconv [--seeds 5] [--batch 512] [--iters 20]
        [--grid BLOCK=64,128 NUM_WARPS=2,4] [--passes forward forward_backward]
    python -m benchmarks.wideconv --pick RESULTS.json [--by forward_backward]

For every seed (vmapped, as the update does), bf16:
- encoder: relu(conv 3x3) x 3 on [batch, 41, 41, 32] -> [batch, 35, 35, 32];
- decoder: relu(transposed conv 3x3, stride 1) x 3 on [batch, 35, 35, 16] -> [batch, 41, 41, 32].
Each as a forward pass alone (as for next_obs) and as forward + backward (input and parameter
gradients of a sum of the outputs), by:
- xla_loop: each convolution once per seed on cuDNN (agent.seed_axis="hybrid", the default);
- pallas: `wideconv.conv_stack`, for each combination of the settings in --grid (names of
  dear_jax/wideconv.py's module settings; a value "None" is None, digits are ints).
Prints ms per call, the host's dispatch per call, and the largest difference from the same pass
in float32 (cuDNN, all seeds at once; per output, relative to its largest magnitude); writes
JSON. With --pick, writes the settings of a results file's fastest variant (both stacks' times
of the pass --by, summed) into dear_jax/wideconv.py as its defaults.
"""

from __future__ import annotations

import argparse
import collections
import itertools
import json
import pathlib
import re

import jax
import jax.numpy as jnp

from benchmarks.common import save_json, timed_calls
from dear_jax import networks, wideconv

STACKS = dict(encoder=(41, (32, 32, 32, 32), 0), decoder=(35, (16, 32, 32, 32), 2))


def _xla_stack(x, layers, pad):
    for k, b in layers:
        x = jnp.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
        x = jax.nn.relu(networks._conv2d(x, k, 1, x.dtype, 8) + b.astype(x.dtype))
    return x


def _programs(impl, pad):
    def stack(x, layers):
        if impl == "pallas":
            return wideconv.conv_stack(x, layers, pad)
        if impl == "float32":
            return _xla_stack(x.astype(jnp.float32), layers, pad)
        with networks.conv_settings(loop_seeds=True):
            return _xla_stack(x, layers, pad)

    def loss(x, layers):
        return jnp.sum(stack(x, layers).astype(jnp.float32))

    forward = jax.jit(jax.vmap(stack))
    both = jax.jit(jax.vmap(jax.value_and_grad(loss, (0, 1))))
    return dict(forward=forward, forward_backward=both)


def parse_grid(items: list[str]) -> list[dict]:
    """["STAGES=2,3", "BLOCK=64"] -> [{"STAGES": 2, "BLOCK": 64}, {"STAGES": 3, "BLOCK": 64}]."""
    axes = {}
    for item in items:
        name, _, values = item.partition("=")
        if not hasattr(wideconv, name) or name != name.upper() or not values:
            settings = sorted(k for k in vars(wideconv) if k.isupper() and k != "INTERPRET")
            raise SystemExit(f"--grid {item!r}: expected NAME=v1,v2 with NAME one of {settings}")
        axes[name] = [
            None if v == "None" else int(v) if v.isdigit() else v for v in values.split(",")
        ]
    return [dict(zip(axes, combo)) for combo in itertools.product(*axes.values())]


def variant_name(settings: dict) -> str:
    return "pallas_" + ("_".join(f"{k.lower()}{v}" for k, v in settings.items()) or "current")


def pick(results: str, by: str, module=pathlib.Path(wideconv.__file__)) -> dict:
    """Write the fastest variant's settings in `results` into `module`'s defaults."""
    total, settings = collections.defaultdict(float), {}
    for r in json.loads(pathlib.Path(results).read_text())["rows"]:
        if r["variant"].startswith("pallas") and r["pass_"] == by and "ms_per_call" in r:
            total[r["variant"]] += r["ms_per_call"]
            settings[r["variant"]] = r["settings"]
    best = min(total, key=total.get)
    text = module.read_text()
    for name, value in settings[best].items():
        # the value replaced, the line's comment kept
        pattern = rf"(?m)^({name}(?:: [^=]+)?) = [^#\n]*?(\s*#.*)?$"
        text, n = re.subn(pattern, rf"\1 = {value!r}\2", text)
        if n != 1:
            raise SystemExit(f"{results}: {name} is not a setting of {module}")
    module.write_text(text)
    print(f"{best}: {total[best]:.3f} ms ({by}, both stacks); written into {module}")
    return settings[best]


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--iters", type=int, default=20)
    p.add_argument("--grid", nargs="+", default=["BLOCK=64,128", "NUM_WARPS=2,4"])
    p.add_argument(
        "--passes",
        nargs="+",
        default=["forward", "forward_backward"],
        choices=["forward", "forward_backward"],
    )
    p.add_argument("--out", default=None)
    p.add_argument("--pick", metavar="RESULTS_JSON", help="write its fastest settings, and stop")
    p.add_argument("--by", default="forward_backward", choices=["forward", "forward_backward"])
    args = p.parse_args()
    if args.pick:
        pick(args.pick, args.by)
        return
    grid = parse_grid(args.grid)
    defaults = {k: getattr(wideconv, k) for k in grid[0]}
    rows = []
    for name, (size, channels, pad) in STACKS.items():
        keys = iter(jax.random.split(jax.random.key(0), 8))
        x = jax.random.normal(next(keys), (args.seeds, args.batch, size, size, channels[0]))
        x = jax.nn.relu(x).astype(jnp.bfloat16)
        layers = tuple(
            (
                jax.random.normal(next(keys), (args.seeds, 3, 3, c, f)) * (2 / (9 * c)) ** 0.5,
                jnp.zeros((args.seeds, f)),
            )
            for c, f in zip(channels, channels[1:])
        )
        # the module's current settings too, so that a sweep can only keep or better them
        choices = [("xla_loop", {}), ("pallas", {})] + [("pallas", g) for g in grid]
        reference = {
            k: [a.astype(jnp.float32) for a in jax.tree.leaves(fn(x, layers))]
            for k, fn in _programs("float32", pad).items()
            if k in args.passes
        }
        one_seed = jax.tree.map(lambda a: a[0], layers)
        for impl, settings in choices:
            variant = variant_name(settings) if impl == "pallas" else impl
            for k, v in {**defaults, **settings}.items():
                setattr(wideconv, k, v)
            for pass_name, fn in _programs(impl, pad).items():
                if pass_name not in args.passes:
                    continue
                if impl == "pallas" and not wideconv.supported(
                    jax.ShapeDtypeStruct(x.shape[1:], x.dtype), one_seed, pad
                ):
                    print(f"{name} {variant}: not supported")
                    continue
                try:
                    out = jax.block_until_ready(fn(x, layers))
                except Exception as e:  # a choice Triton cannot compile is reported, not fatal
                    print(f"{name} {variant} {pass_name}: {type(e).__name__}: {str(e)[:300]}")
                    rows.append(
                        dict(
                            stack=name,
                            variant=variant,
                            settings=settings,
                            pass_=pass_name,
                            error=str(e)[:500],
                        )
                    )
                    continue
                flat = [a.astype(jnp.float32) for a in jax.tree.leaves(out)]
                ref = reference[pass_name]
                error = max(
                    float(jnp.max(jnp.abs(a - b)) / (jnp.max(jnp.abs(b)) + 1e-30))
                    for a, b in zip(flat, ref)
                )
                ms, dispatch = timed_calls(lambda _, fn=fn, x=x, ws=layers: fn(x, ws), args.iters)
                rows.append(
                    dict(
                        stack=name,
                        variant=variant,
                        settings=settings,
                        pass_=pass_name,
                        ms_per_call=ms,
                        ms_per_seed=ms / args.seeds,
                        dispatch_ms_per_call=dispatch,
                        error=error,
                    )
                )
                print(f"{name} {variant} {pass_name}: {ms:.3f} ms/call, error {error:.1e}")
    device = jax.devices()[0].device_kind
    print(f"{device}, jax {jax.__version__}: {args.seeds} seeds, batch {args.batch}, bf16")
    print(
        "| stack | variant | pass | ms per call | ms per seed | host dispatch ms | max rel. diff |"
    )
    print("|---|---|---|---:|---:|---:|---:|")
    for r in rows:
        if "ms_per_call" in r:
            print(
                f"| {r['stack']} | {r['variant']} | {r['pass_']} | {r['ms_per_call']:.3f} | "
                f"{r['ms_per_seed']:.3f} | {r['dispatch_ms_per_call']:.3f} | {r['error']:.1e} |"
            )
        else:
            print(f"| {r['stack']} | {r['variant']} | {r['pass_']} | failed | | | |")
    save_json(
        dict(device=device, jax=jax.__version__, args=vars(args), rows=rows),
        args.out,
        "benchmarks/results/wideconv_gpu.json",
    )


if __name__ == "__main__":
    main()
