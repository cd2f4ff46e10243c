"""benchmarks/roofline.py: one layer's FLOPs and bytes worked out by hand; totals add up."""

import json
import pathlib

import pytest

from benchmarks import roofline
from dear_jax.update import AgentConfig


def test_conv_cost_by_hand():
    # The trunk's second layer: 41x41x32 bf16 -> 39x39x32 bf16, 3x3, stride 1.
    cost = roofline.conv_cost(41, 32, 32, 3, 1, 2, 2)
    assert cost["side_out"] == 39
    assert cost["flops"] == 2 * 39 * 39 * (3 * 3 * 32) * 32 == 28_035_072
    assert cost["x"] == 41 * 41 * 32 * 2 == 107_584
    assert cost["y"] == 39 * 39 * 32 * 2 == 97_344
    assert cost["w"] == (3 * 3 * 32 * 32 + 32) * 4 == 36_992
    # The first layer reads uint8 frames with stride 2: 84 -> 41.
    assert roofline.conv_cost(84, 9, 32, 3, 2, 1, 2)["side_out"] == 41


def test_layer_rows_by_hand():
    batch = 4
    rows = roofline.layers(AgentConfig(action_dim=6, compute_dtype="bfloat16"), batch)
    conv2 = {r.phase: r for r in rows if r.row.startswith("conv 2 ")}
    per_image, x, y, w = 28_035_072, 107_584, 97_344, 36_992
    # forward on obs and next_obs; backward (input and weight gradients) on obs only
    assert conv2["forward"].flops == 2 * batch * per_image
    assert conv2["forward"].bytes == 2 * batch * (x + y) + w
    assert conv2["backward"].flops == 2 * batch * per_image
    assert conv2["backward"].bytes == 2 * (batch * (x + y) + w)
    # the first layer has only its weight gradient
    conv1 = {r.phase: r for r in rows if r.row.startswith("conv 1 ")}
    assert conv1["backward"].flops == conv1["forward"].flops / 2
    # the encoder's Linear layer 2048 -> 4096: bf16 input, float32 latent
    dense = {r.phase: r for r in rows if r.part == "encoder" and r.row.startswith("Dense")}
    assert dense["forward"].flops == 2 * (2 * batch) * 2048 * 4096
    assert dense["forward"].bytes == 2 * batch * (2048 * 2 + 4096 * 4) + (2048 * 4096 + 4096) * 4


def test_dear_floor_at_batch_512():
    """The committed roofline (roofline_dear_bf16_b512.json, benchmarks/RESULTS.md's figures) is
    what the code computes; FLOPs are all per sample (the Adam step and EMA count bytes only), so
    batch 512's are 128x batch 4's, while the weights' bytes do not scale with the batch."""
    cfg = AgentConfig(action_dim=6, compute_dtype="bfloat16")
    total = roofline.summarize(roofline.layers(cfg, 512))["total"]
    path = (
        pathlib.Path(__file__).parents[1]
        / "benchmarks/results/roofline/roofline_dear_bf16_b512.json"
    )
    committed = json.loads(path.read_text())["total"]
    assert (total["flops"], total["bytes"]) == (committed["flops"], committed["bytes"])
    assert total["floor_us"] == pytest.approx(committed["floor_us"], rel=1e-12)
    small = roofline.summarize(roofline.layers(cfg, 4))["total"]
    assert total["flops"] == 128 * small["flops"]
    assert small["bytes"] < total["bytes"] < 128 * small["bytes"]


def test_totals_add_up():
    summary = roofline.summarize(roofline.layers(AgentConfig(action_dim=6), 8))
    total = summary["total"]
    for key in ("flops", "bytes", "floor_us"):
        assert sum(p[key] for p in summary["parts"]) == pytest.approx(total[key])
        assert sum(r[key] for r in summary["rows"]) == pytest.approx(total[key])
        assert sum(x[key] for x in summary["layers"]) == pytest.approx(total[key])
    for x in summary["layers"]:
        assert x["floor_us"] == pytest.approx(max(x["compute_us"], x["memory_us"]))


def test_each_method_counts_its_own_parts():
    """DrQ-v2 is DEAR's encoder, critic and actor without its decoder and orthogonality loss;
    SEAR adds a reconstruction decoder of the 9-channel frames; TED encodes a third batch."""
    batch = 4
    rows = {
        m: roofline.layers(AgentConfig(action_dim=6, method=m, compute_dtype="bfloat16"), batch)
        for m in ("dear", "drqv2", "sear", "ted")
    }
    parts = {m: {r.part for r in r_} for m, r_ in rows.items()}
    assert {m for m, p in parts.items() if "mask decoder" in p} == {"dear", "sear"}
    assert {m for m, p in parts.items() if "recon decoder" in p} == {"sear"}
    drqv2 = {(r.part, r.name, r.phase): r for r in rows["drqv2"]}
    shared = [r for r in rows["dear"] if r.part not in ("mask decoder", "losses", "optimizer")]
    assert shared and all(drqv2[(r.part, r.name, r.phase)] == r for r in shared)
    assert sum(r.bytes for r in rows["dear"]) > sum(r.bytes for r in rows["drqv2"])

    def conv2_forward(method):
        return next(r for r in rows[method] if r.row.startswith("conv 2 ") and r.phase == "forward")

    assert conv2_forward("ted").flops == 3 * batch * 28_035_072  # obs, next_obs, a far frame
    assert conv2_forward("sear").flops == conv2_forward("dear").flops

    def conv2_backward(method):
        return next(
            r for r in rows[method] if r.row.startswith("conv 2 ") and r.phase == "backward"
        )

    # only z_t is differentiated: one backward pass in every method
    assert conv2_backward("ted") == conv2_backward("dear") == conv2_backward("drqv2")
    # SEAR's loss pass: read the bf16 output and the uint8 frames, write the output's gradient
    (loss,) = [r for r in rows["sear"] if r.row == "reconstruction loss"]
    assert loss.bytes == batch * 84 * 84 * 9 * (2 + 1 + 2)
    (mask_loss,) = [r for r in rows["sear"] if r.row == "mask loss"]
    assert mask_loss.bytes == batch * 84 * 84 * 3 * (2 + 1 + 2)
