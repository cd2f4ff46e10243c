"""Reference levels for the logged cosine between the latent halves, cos(z_A, z_E).

    python -m benchmarks.cosine_floor [--dim 2048] [--pairs 20000] [--out FILE]

Nothing is trained; all on the CPU, in float64 unless said. Three figures that say what a
logged |cos| means at the latent's width (`agent.latent_dim` / 2 per half):
  * unrelated halves: mean |cos| of independent Gaussian pairs (sampled, and the exact value
    Gamma(d/2) / (sqrt(pi) Gamma((d+1)/2)), about sqrt(2 / (pi d))). A method with no loss on
    the cosine whose halves carry unrelated directions sits here.
  * the precision floor: pairs made exactly orthogonal, their components rounded to bfloat16
    (as the bf16 encoder's last Linear writes z) or to float32, the cosine then computed in
    float32 as `losses.cosine_similarity` does: the |cos| that rounding alone leaves.
  * the signed mean: for cosines of magnitude m and random sign, the mean over n independent
    samples has a spread of about m / sqrt(n); printed for the evaluation's n.
Writes JSON (benchmarks/results/cosine_floor.json by default).
"""

from __future__ import annotations

import argparse
import math

import ml_dtypes
import numpy as np

from benchmarks.common import save_json


def unrelated_abs_cos(dim: int) -> float:
    """E|cos| of two independent isotropic vectors in `dim` dimensions."""
    return math.exp(math.lgamma(dim / 2) - math.lgamma((dim + 1) / 2)) / math.sqrt(math.pi)


def _cos32(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = a.astype(np.float32), b.astype(np.float32)
    return np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))


def orthogonal_pairs(rng: np.random.Generator, pairs: int, dim: int):
    """Gaussian a and b with b made exactly orthogonal to a (in float64)."""
    a = rng.standard_normal((pairs, dim))
    b = rng.standard_normal((pairs, dim))
    b -= np.sum(a * b, -1, keepdims=True) / np.sum(a * a, -1, keepdims=True) * a
    return a, b


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--dim", type=int, default=2048, help="width of one latent half")
    parser.add_argument("--pairs", type=int, default=20_000)
    parser.add_argument("--eval-samples", type=int, default=5000, help="10 episodes x 500 steps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)

    a = rng.standard_normal((args.pairs, args.dim))
    b = rng.standard_normal((args.pairs, args.dim))
    cos = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    oa, ob = orthogonal_pairs(rng, args.pairs, args.dim)
    floors = {
        name: float(np.mean(np.abs(_cos32(oa.astype(dt), ob.astype(dt)))))
        for name, dt in (("bfloat16", ml_dtypes.bfloat16), ("float32", np.float32))
    }
    result = {
        "dim": args.dim,
        "pairs": args.pairs,
        "unrelated_abs_cos_exact": unrelated_abs_cos(args.dim),
        "unrelated_abs_cos_sampled": float(np.mean(np.abs(cos))),
        "unrelated_signed_cos_sampled": float(np.mean(cos)),
        "orthogonal_abs_cos_after_rounding": floors,
        "eval_samples": args.eval_samples,
        "signed_mean_spread_per_unit_abs_cos": 1 / math.sqrt(args.eval_samples),
    }
    print(f"latent half of {args.dim}: unrelated halves |cos| = {unrelated_abs_cos(args.dim):.4e}")
    print(f"  sampled over {args.pairs} pairs: |cos| {result['unrelated_abs_cos_sampled']:.4e}")
    for name, value in floors.items():
        print(f"  exactly orthogonal, rounded to {name}: |cos| {value:.3e}")
    print(
        f"  signed mean of {args.eval_samples} independent cosines of magnitude m: spread "
        f"~{result['signed_mean_spread_per_unit_abs_cos']:.3g} m"
    )
    save_json(result, args.out, "benchmarks/results/cosine_floor.json")


if __name__ == "__main__":
    main()
