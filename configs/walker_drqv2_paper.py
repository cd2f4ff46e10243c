"""DrQ-v2 on walker-walk with DrQ-v2's own walker_walk settings: the learning check against its
published curves (facebookresearch/drqv2 curves/dmc_walker_walk.csv).

DrQ-v2's plain encoder (flattened convs, no pooling), its "easy task" exploration schedule (std
1.0 -> 0.1 over 100k agent steps), nstep 1 and batch 512 (its walker override). It trains 500k
frames (`total_frames`); its replay of 500k transitions would hold every transition even of a
1M-frame run, as DrQ-v2's 1M-entry buffer does (500k transitions at action repeat 2). bf16
convolutions and 16 envs per seed: the fast GPU path (benchmarks/RESULTS.md);
`--config.agent.compute_dtype=float32` is the fp32 path.
"""

from configs.base import make


def get_config():
    c = make("walker", "drqv2", distraction="none")
    c.agent.encoder = "plain"
    c.agent.std_steps = 100_000
    c.agent.nstep = 1
    c.agent.batch_size = 512
    c.agent.compute_dtype = "bfloat16"
    c.envs_per_seed = 16
    c.total_frames = 500_000
    c.replay.capacity = 500_000
    return c
