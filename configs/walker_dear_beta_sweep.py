"""The paper's beta ablation in one run: DEAR on distracting walker-walk (the paper's setting:
medium, background videos) with beta in {-1 (a negative weight: the halves pulled together), 0,
1, 10, 100}, 3 seeds each: 15 lanes of one compiled program (dear_jax/lanes.py). Lanes of one seed start from the same parameters.

15 lanes' replays must share the GPU: 100k transitions per lane (the last 200k frames; the
other experiments keep 250k), 42 GB in all at 84x84.
`python -m dear_jax.report curves runs/walker_dear_beta_sweep` draws a line per beta.
"""

from configs import paper


def get_config():
    c = paper.get_config("walker,dear,medium")
    c.sweep.beta = "-1,0,1,10,100"
    c.replay.capacity = 100_000
    return c
