"""DEAR's two losses ablated in one run, distracting walker-walk (the paper's setting: medium,
background videos): alpha in {0.25, 0} (mask loss on, off) crossed with beta in {100, 0}
(orthogonality on, off), 3 seeds each: 12 lanes. alpha = beta = 0 is DrQ-v2 on DEAR's encoder. 100k transitions per lane, as in
walker_dear_beta_sweep.py.
"""

from configs import paper


def get_config():
    c = paper.get_config("walker,dear,medium")
    c.sweep.alpha = "0.25,0"
    c.sweep.beta = "100,0"
    c.replay.capacity = 100_000
    return c
