"""Franka Kitchen experiments (docs/method.md): the base hyperparameters with the kitchen's env.

Everything else stays the base's (docs/method.md: batch 256, n-step 3, lr 1e-4, std 1.0 -> 0.1 over 500k
agent steps, 4000 seed frames, 2000 uniform steps, eval every 10k frames over 10 episodes). With
action repeat 1 a frame is an agent step, and an episode is at most 280 frames (it ends on
success); eval logs and the run summary report the success rate.
"""

from ml_collections import ConfigDict

from configs.base import get_config

KITCHEN_TASKS = {"light": "kitchen-light", "kettle": "kitchen-kettle"}


def make(task: str, method: str) -> ConfigDict:
    """The config of one kitchen experiment: task short name ("light", "kettle"), method."""
    c = get_config()
    c.env.task = KITCHEN_TASKS[task]
    c.env.action_repeat = 1  # 40 physics steps of 2 ms per agent step, as in D4RL
    c.env.backend = "auto"  # MJX on an accelerator (measured there); CPU MuJoCo's cost not measured
    c.env.episode_frames = 0  # the task's 280 steps
    c.agent.method = method
    return c
