"""A tiny DEAR run on walker-walk that finishes in a few minutes on a 2-core CPU machine.

It exercises everything a real run does (seeding, uniform exploration, updates, evaluation,
videos, checkpoints, logs, summary) at toy scale: short episodes, a small batch, few frames.
"""

from configs.base import get_config as base_config


def get_config():
    c = base_config()
    c.seeds = 2
    c.envs_per_seed = 2
    c.total_frames = 1200
    c.eval_every_frames = 600
    c.num_eval_episodes = 1
    c.log_every_frames = 200
    c.checkpoint_every_frames = 600
    c.env.episode_frames = 200  # 100 agent steps per episode
    c.env.render.num_workers = 2
    c.env.render.quality = "fast"  # dm_control's effects cost ~7x on Mesa llvmpipe
    c.agent.batch_size = 16
    # Narrow networks: checkpoints of ~22 MB instead of ~310 MB (a DEAR seed at the paper's
    # widths holds ~14.3M parameters, ~160 MB with its optimiser state).
    c.agent.latent_dim = 256
    c.agent.hidden_dim = 256
    c.agent.explore_steps = 200
    c.replay.capacity = 4000
    c.replay.seed_frames = 400
    c.replay.chunk_entries = 200  # replay files of 100 rows: the run writes a few
    return c
