"""Franka Kitchen experiments (docs/method.md): the base hyperparameters with the kitchen's env.

Everything else stays the base's (docs/method.md: batch 256, n-step 3, lr 1e-4, std 1.0 -> 0.1 over 500k
agent steps, 4000 seed frames, 2000 uniform steps, eval every 10k frames over 10 episodes). With
action repeat 1 a frame is an agent step, and an episode is at most 280 frames (it ends on
success); eval logs and the run summary report the success rate. The paper's exploration (a new
draw every agent step) never reached the light switch here; `paper.py:light,METHOD,noise_hold=20`
holds each draw 20 agent steps, with which DEAR learned it by 80k frames (docs/method.md, decision 17).
"""

from ml_collections import ConfigDict

from configs import base

KITCHEN_TASKS = {"light": "kitchen-light", "kettle": "kitchen-kettle"}


def get_config(spec: str | None = None) -> ConfigDict:
    """Not a run's config: the kitchen's runs are named in paper.py."""
    raise ValueError(
        "configs/kitchen.py holds the kitchen's settings, not a run: train with "
        "--config paper.py:light,METHOD or paper.py:kettle,METHOD (METHOD: dear, sear, ted, drqv2)"
    )


def make(task: str, method: str) -> ConfigDict:
    """The config of one kitchen experiment: task short name ("light", "kettle"), method."""
    c = base.get_config()
    c.env.task = KITCHEN_TASKS[task]
    c.env.action_repeat = 1  # 40 physics steps of 2 ms per agent step, as in D4RL
    # CPU MuJoCo, stepped on threads beside the accelerator's updates, as the DMC tasks: one
    # kitchen agent step (40 physics steps) costs ~1.8 ms per env on one CPU thread, where MJX
    # took 75 ms for 40 envs on an H100
    # (results/README.md, "Franka Kitchen"; benchmarks/RESULTS.md, "Franka Kitchen physics").
    # tests/test_kitchen.py checks both backends.
    c.env.backend = "cpu"
    # 3 x 16 envs took 11.7 ms per agent step on 16 threads, 17.8 on 8, on an H100 machine's 16
    # cores (benchmarks/RESULTS.md, "Franka Kitchen physics"); threads beyond the cores a run may
    # use only take turns.
    c.env.physics_threads = 16
    # No shadows, reflections or multisampling: a Hopper GPU has few raster units, and the
    # kitchen's four shadow-casting lights over 142k mesh faces held its pictures to ~300 per
    # second whatever the number of render workers; "fast" draws ~1,500 (benchmarks/RESULTS.md,
    # "Franka Kitchen rendering"). "dm_control" is the reference's picture.
    c.env.render.quality = "fast"
    # The arm's nine meshes (134k of the scene's 142k faces) drawn simplified to 1,000 faces each,
    # and the 53 spheres, capsules and cylinders it shows with 16 slices and 4 stacks instead of
    # MuJoCo's 28 and 16: "fast" frames 1.4 and 0.2 of 255 levels per pixel from the shipped
    # meshes' and from MuJoCo's primitives' (298 of 226k mask pixels differ from the shipped
    # scene's), and the DEAR loop on an H200 1,054-1,068 env frames/s against 919-962 with
    # MuJoCo's primitives and 853-897 with 4,000 faces (benchmarks/RESULTS.md, "Kitchen end to
    # end"). Physics keeps the shipped meshes. 0 draws the shipped meshes, MuJoCo's primitives.
    c.env.render.mesh_faces = 1000
    c.env.render.num_slices = 16
    c.env.render.num_stacks = 4
    # The kitchen's heavier pictures want every worker: 3 seeds x 16 envs on 8 workers drew 852-867
    # env frames/s, on 6 or 3 (8 or 16 envs each) 830-854 (benchmarks/RESULTS.md, "Kitchen end
    # to end").
    c.env.render.envs_per_worker = 0
    c.env.episode_frames = 0  # the task's 280 steps
    c.agent.method = method
    return c
