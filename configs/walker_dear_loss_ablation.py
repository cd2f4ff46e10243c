"""DEAR's two losses ablated in one run, distracting walker-walk (medium): alpha in {0.25, 0}
(mask loss on, off) crossed with beta in {100, 0} (orthogonality on, off), 3 seeds each: 12
lanes. alpha = beta = 0 is DrQ-v2 on DEAR's encoder. 100k transitions per lane, as in
walker_dear_beta_sweep.py.
"""

from configs.base import make


def get_config():
    c = make("walker", "dear", distraction="medium")
    c.sweep.alpha = "0.25,0"
    c.sweep.beta = "100,0"
    c.replay.capacity = 100_000
    return c
