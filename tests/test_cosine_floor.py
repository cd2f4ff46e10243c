"""The reference levels of benchmarks/cosine_floor.py against values computed by hand."""

import math

import ml_dtypes
import numpy as np
import pytest

from benchmarks.cosine_floor import _cos32, orthogonal_pairs, unrelated_abs_cos


@pytest.mark.parametrize(
    "dim, expected",
    [(2, 2 / math.pi), (3, 0.5), (4, 4 / (3 * math.pi))],  # E|cos| of a uniform direction
)
def test_unrelated_abs_cos_in_low_dimensions(dim, expected):
    assert unrelated_abs_cos(dim) == pytest.approx(expected, rel=1e-12)


def test_unrelated_abs_cos_matches_sampling_and_the_large_dim_limit():
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((2, 4000, 64))
    cos = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    assert np.mean(np.abs(cos)) == pytest.approx(unrelated_abs_cos(64), rel=0.03)
    assert unrelated_abs_cos(2048) == pytest.approx(math.sqrt(2 / (math.pi * 2048)), rel=1e-3)


def test_orthogonal_pairs_are_orthogonal_until_rounded():
    a, b = orthogonal_pairs(np.random.default_rng(1), 100, 256)
    exact = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    assert np.max(np.abs(exact)) < 1e-14
    f32 = np.mean(np.abs(_cos32(a.astype(np.float32), b.astype(np.float32))))
    bf16 = np.mean(np.abs(_cos32(a.astype(ml_dtypes.bfloat16), b.astype(ml_dtypes.bfloat16))))
    assert 0 < f32 < 1e-6 < bf16 < 1e-3
