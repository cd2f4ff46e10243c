"""Base configuration: every field, with the hyperparameters of docs/method.md shared by all tasks.

Experiment files start from `make(task, method)`, which adds the per-task settings (walker:
n-step 1 and batch 512, DrQ-v2's), or from `get_config` (the shared defaults alone, n-step 3 and
batch 256 whatever env.task says) and override a few fields; every field can also be overridden
on the command line: `python run.py --config configs/walker_dear.py --config.seeds=5`.
"""

from ml_collections import ConfigDict, config_dict

from dear_jax.lanes import default_sweep

TASK_SHORT_NAMES = {"walker": "walker-walk", "cup": "ball_in_cup-catch", "finger": "finger-spin"}


def get_config() -> ConfigDict:
    c = ConfigDict()
    c.seed = 0  # base seed; seed i of the run uses fold_in(key(seed), i)
    c.seeds = 3  # seeds trained together in one process (a vmapped axis)
    # Devices the seeds are split over (an int, or "all": every local device); seeds must be a
    # multiple of it. Each device runs its block of seeds (agent, replay, envs); 1: one device.
    # With several processes (run.py --multihost), the devices of each process, and the seeds
    # are first split evenly over the processes.
    c.devices = config_dict.FieldReference(1, field_type=object)  # int or "all"
    # Devices each seed's update is split over (devices must be a multiple of it): each holds the
    # whole seed (agent, replay), draws its share of the batch, and the gradients are averaged.
    # One process only. A walker SEAR seed (batch 512) made 609 env frames/s on 2 H200s with
    # evaluations, against 678 on one (benchmarks/RESULTS.md, "Several GPUs").
    c.devices_per_seed = 1
    # Parallel environments per seed; E / update_every_steps updates per step. DEAR walker-walk,
    # 5 seeds, H100: 704 / 731 / 732 / 736 frames/s at 4 / 8 / 16 / 32
    # (benchmarks/results/train_envs_{4,8,16,32}_h100.json).
    c.envs_per_seed = 8
    # Frames count per seed, summed over its envs: frames = agent steps (all E envs) x action repeat.
    c.total_frames = 1_000_000  # environment frames per seed
    c.eval_every_frames = 10_000  # per seed
    c.num_eval_episodes = 10  # per seed, run in parallel
    # Evaluate in a background thread on a copy of the parameters while training goes on (the
    # row is logged with the frame it started at); False: training waits for each evaluation.
    c.eval_in_background = True
    # Where evaluations run: "cpu", a process of their own on the host's CPU (its own Python,
    # XLA:CPU with the policy in float32, render workers), so that evaluating takes neither the
    # accelerator's queue nor this process's threads from the training; "accelerator", such a
    # process with the training's policy program on the accelerator (the first GPU the training
    # leaves idle, if any: start a run with one GPU more to evaluate there); "train", this process on
    # the training's devices and agent.compute_dtype; "auto": "accelerator" for a run of one
    # process on a GPU (it slowed training least there), "cpu" on a CPU-only machine, "train"
    # for a run of several processes (their evaluations are programs over every process's lanes).
    c.eval_device = "auto"
    # Evaluation processes side by side ("cpu" or "accelerator"): the evaluation at frame f runs
    # in process f // eval_every_frames mod N, each with its own stream of episodes, all on the
    # upper half of the run's cores (dear_jax/evaluator.py). More than one lets the next
    # evaluation start while one still runs, where one outlasts the training between two (on
    # the paper's grid an evaluation takes ~10 s, and one seed trains 10k frames in 6.4-8 s: with
    # one process, finger's DEAR waited 21% of its run for them; `python -m dear_jax.report evals
    # RUN` tells; benchmarks/RESULTS.md). 0: two on a GPU machine, one on a CPU-only one.
    c.eval_processes = 0
    # Niceness the evaluation processes add to their own (0-19): above 0 the training's threads
    # go first where they share cores with an evaluation's physics and render workers.
    c.eval_nice = 0
    c.log_every_frames = 5_000  # per seed: train metrics to CSV / TensorBoard
    c.checkpoint_every_frames = 100_000  # per seed; 0 disables periodic checkpoints
    c.keep_checkpoints = 3  # the latest checkpoints kept (orbax deletes older ones)
    c.save_video = True  # eval video of env 0 per seed: RGB | true mask | predicted mask
    c.progress = True  # tqdm progress bar on a terminal (else a log line per log interval)
    # A jax.profiler trace of `profile.iterations` loop iterations from frame `profile.at_frame`
    # per seed (-1: off; a run resumed past that frame takes none), written to workdir/profile
    # (TensorBoard's Profile tab, or Perfetto).
    c.profile = ConfigDict()
    c.profile.at_frame = -1
    c.profile.iterations = 20

    c.env = ConfigDict()
    c.env.task = "walker-walk"  # python -c "import envs; print(envs.names())" lists them
    # Physics: "cpu" (CPU MuJoCo with dm_control's own solver and stepping, run on the env thread
    # while the accelerator updates), "mjx" (batched on the accelerator) or "auto" (MJX when an
    # accelerator is present). "cpu" is the default, for the DMC tasks: on an H100 the MJX step's
    # solver loops made the host wait for every queued update, leaving the GPU idle for a third
    # of each iteration (benchmarks/RESULTS.md, "End to end"); CPU MuJoCo is also dm_control's
    # physics exactly. Runs made before 2026-11-23 evening used "auto" and resume with
    # --config.env.backend=auto. The kitchen (configs/kitchen.py) steps "cpu" too.
    c.env.backend = "cpu"
    # Physics of the evaluation episodes: "cpu" (CPU MuJoCo, dm_control's own solver and
    # stepping, on CPU cores beside the GPU's training) or "train" (env.backend's).
    c.env.eval_backend = "cpu"
    # Threads of the training env's CPU physics (the same numbers on any count); 0: one per
    # device the process trains on (one device: one thread, overlapped with the updates).
    c.env.physics_threads = 0
    # Threads of the evaluation env's CPU physics; 0: one per core the evaluating process may
    # use, up to 8 (the evaluation process has half the machine's cores).
    c.env.eval_physics_threads = 0
    # Python's thread switch interval (ms) while the loop runs; 0: Python's own (5 ms). The env's
    # threads take the GIL back several times per env and step and may each time wait this long
    # for the loop's thread to let go (benchmarks/gil.py measures it).
    c.env.switch_interval_ms = 0.0
    c.env.distraction = "none"  # "none" | "easy" | "medium" | "hard" (Distracting Control Suite)
    # Which distractions, comma-separated: any of background, color, camera, or "all" (the full
    # suite). The paper's setting (configs/paper.py) is "background".
    c.env.distraction_types = "all"
    c.env.dynamic = False  # distractions move during the episode
    c.env.background_dir = ""  # DAVIS-2017 root; "" = built-in procedural videos (logged)
    c.env.mask = "true"  # training mask: "true" | "noisy" | "approximate" (ablations)
    c.env.mask_drop_prob = 0.8  # for mask="noisy"
    c.env.action_repeat = 2  # env frames per agent step (the same action repeated)
    c.env.episode_frames = 0  # 0 = the task's own length (1000 frames for DMC)
    c.env.render = ConfigDict()
    # "dm_control": the frames dm_control's physics.render draws (skybox, shadows, reflections,
    # multisampling), as published curves learned from; "fast": none of these effects (a black
    # sky; a different picture), ~7x cheaper on CPU-only machines, 5x on an H100 drawing the
    # kitchen (its default: docs/method.md, decision 16). See envs/render.py.
    c.env.render.quality = "dm_control"
    c.env.render.num_workers = 0  # 0 = min(cores, 8) per environment batch
    # With num_workers 0: at least this many envs per worker (0: no cap), each worker a GL
    # context on the GPU it draws on (env.render.gpus). One walker seed of 16 envs on 2 workers
    # rather than 8: 958-968 env frames/s against 886-941 on an H200; 5 seeds of 16 (8 workers
    # against 5) level (benchmarks/RESULTS.md, "End to end").
    c.env.render.envs_per_worker = 8
    # Meshes of more faces drawn simplified to about this many (0: as shipped, or >= 1000): only
    # the kitchen's arm has such meshes (envs/kitchen.py, build_render_model).
    c.env.render.mesh_faces = 0
    # Spheres, capsules and cylinders drawn with this many slices around and stacks along (0:
    # the model's own, MuJoCo's 28 and 16 unless it says otherwise); fewer draw faster.
    c.env.render.num_slices = 0
    c.env.render.num_stacks = 0
    # The GPUs the render workers draw on: "auto", GPUs of this process that the training leaves
    # idle (where evaluations on the accelerator run: start a run with one GPU more), else those
    # that train the env's lanes (an evaluation's: its policy's; MUJOCO_EGL_DEVICE_ID instead where
    # it is set), or GPU numbers of this process, e.g. "0": beside the updates; "cpu": Mesa's
    # llvmpipe on the cores (for GPUs without EGL; 0.63x DEAR walker's frames/s). Drawing slows the
    # updates on their GPU: DEAR walker's loop, 5 lanes, drawn on a second GPU ran at 1,709-1,711
    # env frames/s against 1,355-1,398, the kitchen's at 1,076 against 879 (benchmarks/RESULTS.md).
    c.env.render.gpus = "auto"

    c.agent = ConfigDict()
    c.agent.method = "dear"  # "drqv2" | "dear" | "sear" | "ted"
    c.agent.encoder = "pool"  # "pool" | "plain" (DrQ-v2's flattened encoder; drqv2 only)
    c.agent.latent_dim = 4096  # the encoder's z = [z_E, z_A], half each (pool encoder)
    c.agent.feature_dim = 50  # the actor's and critic's input layer: Linear, LayerNorm, Tanh
    c.agent.hidden_dim = 1024  # the actor's and each critic head's hidden layers
    c.agent.lr = 1e-4  # Adam: encoder, decoders, critic, actor
    c.agent.ted_lr = 1e-3  # Adam: TED's classifier
    # "bfloat16": encoder/decoder convolutions in bf16 (parameters stay float32); the DEAR update
    # at batch 512 took 6.1 instead of 10.3 ms on an H100 (benchmarks/results/update_h100_512.json).
    c.agent.compute_dtype = "float32"
    # How the update runs over seeds inside one program: "hybrid" (vmapped, each convolution once
    # per seed), "loop" (one traced update per seed) or "vmap" (grouped convolutions). Same
    # numbers. On an H100, bf16, 5 seeds, batch 512 (benchmarks/results/update_axes_h100.json):
    # DEAR 5.10 ms per seed hybrid, 5.20 loop; DrQ-v2 3.08 and 3.21; compiling took 23 s instead
    # of 65 s. vmap was 1.5x slower than loop (benchmarks/results/update_h100.json).
    c.agent.seed_axis = "hybrid"
    # How the random shift is computed: "gather" | "pad_slice" | "one_hot" (dear_jax.augment).
    # Same pixels; "gather" made the bf16 DEAR update 5.21 instead of 5.48 ms per seed on an H100
    # (benchmarks/results/update_shift_h100.json).
    c.agent.shift_impl = "gather"
    # The convolutions' filter gradients: "cudnn" (XLA's) or "pallas" (dear_jax/wgrad.py, one
    # kernel for all seeds; stride-1 layers with power-of-2 channels). Same numbers. cuDNN's cost
    # the host more to launch than they run on an H100 (benchmarks/results/dispatch_h100.json);
    # "pallas" launches cheaply, but the update ran 2-3% slower with it
    # (benchmarks/results/update_pallas_h100.json).
    c.agent.filter_gradient = "cudnn"
    # The conv layers of the encoder and decoders: "xla" (cuDNN, layer by layer), "pallas"
    # (dear_jax/wideconv.py: each stack as Pallas kernels, bias/ReLU fused, one launch per layer
    # for all seeds, the first layer reading the uint8 frames through the random shift) or
    # "auto": "pallas" on GPUs, "xla" elsewhere (Pallas would run in its interpreter). Same
    # function. On an H100 "pallas" made the bf16 DEAR update of 5 seeds at batch 512 3.03
    # instead of 5.01 ms per seed, and DEAR walker runs with it learned within the spread of
    # those with cuDNN (benchmarks/RESULTS.md).
    c.agent.conv_stack = "auto"
    # The Pallas stacks' kernel constants for the update, "NAME=INT,..." (dear_jax.wideconv:
    # TUNABLE, e.g. "WGRAD_MIN_PROGRAMS=1024,BLOCK=256"); "": the module's values, the fastest
    # of the H100 sweeps. Same function (rounding aside: wideconv.WGRAD_MIN_PROGRAMS); with the
    # XLA stack it changes nothing. `benchmarks/update.py --conv-stacks pallas --kernels ...`
    # times settings.
    c.agent.kernels = ""
    # Updates per call of the update program (a scan of them): fewer launches where dispatching
    # them sets the loop's pace. 0: on a GPU all of an iteration's (envs_per_seed /
    # update_every_steps), on a CPU 1 (a scan compiles slower there). Where K divides an
    # iteration's updates (DMC) they are the same updates, their keys alike; elsewhere (the
    # kitchen's envs end apart) the rest waits for the next iteration. A lone seed's walker on an
    # H200 with the default xla_options: 1,200 and 1,262 env frames/s with 8 (all of an
    # iteration's) against 987 and 1,045 with 1; 5 seeds level (benchmarks/RESULTS.md).
    c.agent.updates_per_call = 0
    # XLA's options for the update program, "NAME=VALUE,..." (jax.jit's compiler_options; its
    # flags without the leading --). The default schedules its command buffers' kernels
    # concurrently: with an iteration's updates a call, a lone seed's loop 4-9% faster and 5
    # seeds' 2% (benchmarks/RESULTS.md). "": XLA's defaults. Same arithmetic either way.
    c.agent.xla_options = "xla_gpu_command_buffer_scheduling_mode=CONCURRENT"
    c.agent.ortho_form = "abs_cos"  # "abs_cos" (paper) | "reference_code" (1 - cos)
    c.agent.alpha = 0.25  # mask loss weight (DEAR, SEAR)
    c.agent.beta = 100.0  # orthogonality loss weight (DEAR)
    c.agent.recon_weight = 1.0  # SEAR
    c.agent.ted_weight = 100.0  # TED
    # TED's negatives and classifier: "strict" (another sample's z_t+n never a sample's own,
    # never a frame of the n-step positive's window, a pair without one dropped, W0 and W1 drawn
    # apart, c from 0) | "reference_code" (TED's code: a plain shuffle, t+-1 excluded only,
    # another sample's frame instead, one orthogonal 2 x F draw for W0 and W1, c = +-1);
    # docs/method.md, decision 8.
    c.agent.ted_form = "strict"
    c.agent.tau = 0.01  # the target critic's EMA rate per update
    c.agent.stddev_clip = 0.3  # the clip of the policy noise in the critic target and actor loss
    c.agent.std_init = 1.0  # exploration noise std, decayed linearly to std_final
    c.agent.std_final = 0.1
    c.agent.std_steps = 500_000  # agent steps of the linear std decay
    c.agent.explore_steps = 2000  # agent steps of uniform random actions per seed
    # agent steps each env keeps one exploration draw; 1 (DrQ-v2, the paper): a new one each step
    c.agent.noise_hold = 1
    c.agent.batch_size = 256  # transitions per seed per update
    c.agent.nstep = 3  # n-step returns
    c.agent.discount = 0.99  # per agent step
    c.agent.update_every_steps = 2  # one update per this many agent steps per seed

    # Settings trained side by side as lanes of one program, crossed with the seeds: comma-
    # separated values of agent fields, e.g. --config.sweep.beta=-1,0,1,10,100 (dear_jax/lanes.py).
    c.sweep = default_sweep()

    c.replay = ConfigDict()
    c.replay.capacity = (
        250_000  # entries per seed (DEAR's; DrQ-v2 used 1M, which does not fit 5 seeds)
    )
    c.replay.seed_frames = 4000  # frames per seed collected before the first update
    # "uniform": every stored start alike; "episode": DrQ-v2's replay, an episode uniformly among
    # the finished ones, then a start in it (docs/method.md, decision 18).
    c.replay.sampling = "uniform"
    # Keep the replay on disk too (workdir/replay/, compressed chunks written as they fill), so a
    # resume continues with it; False: a resume starts with an empty replay and refills it.
    c.replay.disk = True
    c.replay.chunk_entries = 2000  # entries per seed per chunk file (~56 MB before compression)
    return c


def make(task: str, method: str, distraction: str = "none") -> ConfigDict:
    """The config of one experiment of the paper's grid: task short name (walker, cup, finger),
    method, Distracting Control difficulty ("none", "easy", "medium", "hard")."""
    c = get_config()
    c.env.task = TASK_SHORT_NAMES[task]
    c.agent.method = method
    if task == "walker":  # DrQ-v2's walker settings
        c.agent.nstep = 1
        c.agent.batch_size = 512
    c.env.distraction = distraction
    return c
