#!/usr/bin/env bash
# The GPU session of the trainer issue, in stages (bash benchmarks/train_device.sh STAGE...):
#   gl        GL_RENDERER of the render workers (must be the GPU, not llvmpipe)
#   profile   benchmarks/profile_update.py (DEAR, DrQ-v2; batch 512) and benchmarks/decoder.py
#   update    benchmarks/update.py: DEAR update at batch 256 (1 and 5 seeds, vmap vs loop), and
#             DEAR / DrQ-v2 at walker's batch 512 (5 seeds, loop)
#   train     benchmarks/train.py: DEAR walker-walk, 5 seeds x 8 envs, stage split, then throughput
#   learn     start DrQ-v2 and DEAR walker-walk (3 seeds each) detached, side by side on the GPU
#   paper     start the learning check detached: ${LEARN_CONFIG:-configs/walker_drqv2_paper.py}
#             (e.g. LEARN_CONFIG=configs/walker_dear.py; several configs, space-separated, train
#             side by side; DTYPES="float32 bfloat16": each config once per dtype;
#             CONFIG:DTYPE: that config in that dtype; configs/paper.py:walker,dear,medium,noisy
#             names a paper.py experiment, in runs/paper_walker_dear_medium_noisy), 3 seeds
#             each, physics of $BACKEND if set,
#             more flags from $LEARN_ARGS (e.g. --config.envs_per_seed=16), from a copy of
#             the tree (keep the machine with `wait`, then `collect`)
#   kitchen   start DEAR on kitchen-light detached (3 seeds x 8 envs, bf16, eval every 10k
#             frames) from a copy of the tree, so a later call's tree sync cannot touch it
#   stop      SIGTERM every training run (`python3 run.py ...`) and wait up to 120 s for their
#             checkpoints and summaries (run before `collect` when the lease is ending)
#   collect   pack the learning runs' logs (no checkpoints, videos or replay) into $OUT/runs.tar.gz
#   speed     the performance issue's update figures: DEAR fp32 / bf16 and DrQ-v2 bf16 at batch
#             512 (5 seeds), the first conv's input paths (benchmarks/encoder_input.py), the
#             bf16 DEAR profile
#   shift     benchmarks/shift.py: the random shift of 5 seeds' batches, three equal ways
#   fast      the shift lead end to end: benchmarks/shift.py; the DEAR bf16 update (5 seeds,
#             batch 512) with each agent.shift_impl; benchmarks/profile_loop.py (DEAR 5 x 16,
#             bf16) with the fastest impl, with XLA's default command buffers and with every
#             op kind in them ($CB_FLAGS)
#   axes      the seed axis and XLA's conv fusion: benchmarks/update.py (DEAR bf16, DrQ-v2 bf16
#             with its plain encoder; 5 seeds, batch 512) with agent.seed_axis loop and hybrid,
#             with and without $CONV_FUSION (and all command buffers); the profile of the
#             hybrid DEAR update (XLA's defaults)
#   evaldev   benchmarks/train.py: the DrQ-v2 learning check's loop evaluating in the background
#             in the training process (eval_device=train), in a process of its own on the host's
#             CPU (cpu) or on the GPU (accelerator), and not at all (none); $EVAL_DEVICES picks
#             (default "cpu accelerator none")
#   envsweep  benchmarks/train.py: DEAR walker-walk, 5 seeds, bf16, no evaluation, with each
#             number of envs per seed in ${ENVS:-4 8 16 32} (the choice of envs_per_seed)
#   gpushare  benchmarks/train.py (the learning check's loop, no evaluation) alone and beside
#             benchmarks/render_load.py (an evaluation's drawing on the GPU, without its physics)
#   pl C S A F  benchmarks/profile_loop.py of config C with S seeds x 16 envs, bf16,
#             agent.seed_axis A, with XLA's conv fusion if F is "cf" ("-": without); another
#             config field from $PL_SET (e.g. PL_SET=agent.filter_gradient=pallas)
#   pallas    the Pallas filter gradient (dear_jax/wgrad.py): benchmarks/wgrad.py (against
#             cuDNN; its images-per-program x warps choices), the fastest choice made wgrad's
#             default in this tree, then benchmarks/update.py (DEAR bf16, DrQ-v2 bf16 plain
#             encoder; 5 seeds, batch 512, hybrid) with cuDNN's and the kernel's filter gradients
#   wideconv  the stride-1 conv stacks as Pallas kernels (dear_jax/wideconv.py): wcsweep, then
#             wcupdate
#   wcsweep   benchmarks/wideconv.py (against cuDNN), one sweep of wideconv's settings per
#             ';'-separated "PASS:NAME=v1,v2 ..." in $WC_SWEEPS, each one's fastest made
#             wideconv's default in this tree (and copied to $OUT/wideconv_chosen.py)
#   wcupdate  benchmarks/update.py (DEAR bf16, DrQ-v2 bf16 plain encoder; 5 seeds, batch 512,
#             hybrid) with agent.conv_stack xla and pallas, benchmarks/train.py (DEAR
#             walker-walk, 5 seeds x 16 envs, bf16, no evaluation) with pallas, and the profile
#             of the DEAR update with pallas (its compiled HLO too)
#   dispatch  benchmarks/dispatch.py: the host's cost per launched op, per kind, with XLA's
#             defaults, its conv fusion, and no autotuning; the DEAR update without autotuning
#   loop      benchmarks/profile_loop.py: where a training iteration's time goes, per program, for
#             DEAR walker-walk (5 seeds x 16 envs) and the DrQ-v2 learning check (3 x 16), bf16,
#             with the physics of $BACKEND (auto, mjx or cpu; default: the config's)
#   torch     benchmarks/torch_reference.py update (DEAR eager and best, batch 512)
#   evalcost  benchmarks/evaluation.py: one evaluation step of the DrQ-v2 learning check (3 seeds x
#             10 episodes), stage by stage, with the policy and the env's arrays on the GPU or
#             on XLA:CPU and CPU physics on 1 or 8 threads, alone
#   evalload  the same beside a training run of the same config
#   evalrun   one whole evaluation as a run's evaluation process runs it (videos written), alone
#   scaling   benchmarks/scaling.py: DEAR walker-walk, 5 seeds x 8 envs per GPU on 1 and 2 GPUs
#             (a machine with 2 GPUs)
#   wait N    sleep N seconds (keeps the call, and so the machine, alive while runs train)
#   finish N  wait up to N seconds for the training runs to end by themselves (a run that
#             reaches total_frames evaluates, saves and writes its summary), then `stop` what
#             is left and `collect`: the last call of a lease, timed to end before its 30 min
# Results land in $OUT (or /tmp/out). On the lent machine, carry .dmc too (benchmarks/device_dmc.sh:
# dm_control's suite models) and put $PWD/.dmc on PYTHONPATH. A JAX_COMPILATION_CACHE_DIR exported
# before `paper` is the runs' cache: filled by a short run in one lease and carried into the next,
# it spares a learning run its compilations (benchmarks/RESULTS.md, thirteenth session).
set -u
out=${OUT:-/tmp/out}
runs=/tmp/runs
# Every op kind in XLA's command buffers (CUDA graphs), from graphs of one op on.
ALL_CB="--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN --xla_gpu_graph_min_graph_size=1"
# Convolutions as cuDNN fusions (which command buffers can hold), an experimental XLA pass.
CONV_FUSION="--xla_gpu_experimental_enable_conv_fusion=true"
NO_AUTOTUNE="--xla_gpu_autotune_level=0"
mkdir -p "$out" "$runs"
# A machine is not always bare: /tmp/runs has held an earlier lease's run (seventh session).
# Before a run starts in $runs/NAME, an earlier folder of that name moves to $runs/earlier, so
# the new run starts from frame 0 instead of resuming it, and `collect` leaves it out.
set_aside() {
  [ -e "$runs/$1" ] || [ -e "$runs/$1.log" ] || return 0
  mkdir -p "$runs/earlier"; local dest="$runs/earlier/$1-$(date +%s)"
  mkdir -p "$dest"; mv "$runs/$1" "$runs/$1.log" "$dest"/ 2>/dev/null
  echo "earlier run $runs/$1 moved to $dest (not resumed, not collected)"
}
while [ $# -gt 0 ]; do
  stage=$1; shift
  echo "=== $stage $(date +%T)"
  case $stage in
    gl) bash benchmarks/envs_device.sh gl ;;
    profile)
      for method in dear drqv2; do
        timeout 150 python3 -m benchmarks.profile_update --method $method --batch 512 \
          --out "$out/profile_$method.json"
      done
      timeout 120 python3 -m benchmarks.decoder --batch 512 --out "$out/decoder.json" ;;
    update)
      timeout 200 python3 -m benchmarks.update --methods dear --seeds 1 5 --seed-axis vmap loop \
        --iters 20 --out "$out/update_256.json"
      timeout 150 python3 -m benchmarks.update --methods dear drqv2 --seeds 5 --seed-axis loop \
        --batch 512 --iters 10 --out "$out/update_512.json" ;;
    train)
      # Two processes, each with its own limit and log file under $OUT, so a slow stage can
      # neither starve the other nor lose its output.
      timeout 330 python3 -m benchmarks.train --config configs/walker_dear.py --seeds 5 --envs 8 \
        --warmup-frames 2400 --frames 8000 --log-every 1600 --skip split \
        --out "$out/train_throughput.json" > "$out/train_throughput.log" 2>&1
      timeout 220 python3 -m benchmarks.train --config configs/walker_dear.py --seeds 5 --envs 8 \
        --reps 5 --skip throughput --out "$out/train_split.json" > "$out/train_split.log" 2>&1
      grep -v warp "$out"/train_throughput.log "$out"/train_split.log | tail -n 40 ;;
    learn)
      for method in drqv2 dear; do
        XLA_PYTHON_CLIENT_MEM_FRACTION=0.45 setsid nohup python3 run.py \
          --config "configs/walker_$method.py" --workdir "$runs/walker_$method" \
          --config.seeds=3 --config.progress=False \
          > "$runs/walker_$method.log" 2>&1 < /dev/null &
      done
      sleep 5; nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv ;;
    paper)
      # Several configs in $LEARN_CONFIG (space-separated) train side by side, each process with
      # an equal share of the GPU's memory; with $DTYPES (e.g. "float32 bfloat16") each config
      # trains once per compute dtype, in <name>_<dtype>; CONFIG:DTYPE names one run's dtype.
      rm -rf /tmp/paper_tree; cp -r "$PWD" /tmp/paper_tree
      # A config file may carry its argument (configs/paper.py:walker,dear,medium,noisy).
      runs_=()
      for lc in ${LEARN_CONFIG:-configs/walker_drqv2_paper.py}; do
        if [[ $lc == *:float32 || $lc == *:bfloat16 ]]; then runs_+=("$lc")
        elif [ -n "${DTYPES:-}" ]; then for d in $DTYPES; do runs_+=("$lc:$d"); done
        else runs_+=("$lc:"); fi
      done
      share=$(python3 -c "print(round(0.9 / ${#runs_[@]}, 3))")
      for r in "${runs_[@]}"; do
        lc=${r%:*}; d=${r##*:}; name=$(basename "${lc%%:*}" .py)
        [[ $lc == *:* ]] && name=${name}_$(echo "${lc#*:}" | tr , _)
        name=$name${d:+_$d}
        set_aside "$name"
        # exec: no shell waits on the run, so a pipe this stage prints into closes when it ends.
        (cd /tmp/paper_tree && XLA_PYTHON_CLIENT_MEM_FRACTION=$share exec setsid nohup python3 run.py \
          --config "$lc" --workdir "$runs/$name" --config.seeds=3 --config.progress=False \
          ${BACKEND:+--config.env.backend=$BACKEND} ${LEARN_ARGS:-} \
          ${d:+--config.agent.compute_dtype=$d} > "$runs/$name.log" 2>&1 < /dev/null &)
      done
      sleep 5; nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv ;;
    kitchen)
      rm -rf /tmp/kitchen_tree; cp -r "$PWD" /tmp/kitchen_tree; set_aside kitchen_light_dear
      (cd /tmp/kitchen_tree && exec setsid nohup python3 run.py --config configs/kitchen_light_dear.py \
        --workdir "$runs/kitchen_light_dear" --config.seeds=3 --config.total_frames=300000 \
        --config.agent.compute_dtype=bfloat16 --config.progress=False \
        > "$runs/kitchen_light_dear.log" 2>&1 < /dev/null &)
      sleep 5; nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv ;;
    stop)
      # By process id: a pattern given to pkill -f would also match this shell's own command line.
      pids=$(pgrep -f '^python3 run.py'); [ -n "$pids" ] && kill -TERM $pids
      for _ in $(seq 60); do pgrep -f '^python3 run.py' > /dev/null || break; sleep 2; done
      pgrep -fa '^python3 run.py' || echo "no training run left" ;;
    collect)
      for f in "$runs"/*.log; do echo "--- $f"; tail -n 4 "$f"; done
      nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv
      tar -C "$runs" --exclude=checkpoints --exclude=videos --exclude=replay --exclude=./earlier -czf "$out/runs.tar.gz" . ;;
    speed)
      export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
      u="timeout 240 python3 -m benchmarks.update --methods dear --seeds 5 --batch 512 --iters 20"
      $u --seed-axis loop --dtypes float32 bfloat16 --out "$out/update_dear.json"
      timeout 200 python3 -m benchmarks.update --methods drqv2 --seeds 5 --batch 512 --iters 20 \
        --seed-axis loop --dtypes bfloat16 --out "$out/update_drqv2.json"
      timeout 150 python3 -m benchmarks.encoder_input --dtypes bfloat16 float32 \
        --out "$out/encoder_input.json"
      timeout 150 python3 -m benchmarks.profile_update --method dear --batch 512 \
        --dtype bfloat16 --out "$out/profile_dear_bf16.json" ;;
    shift)
      timeout 200 python3 -m benchmarks.shift --seeds 5 --batch 512 --out "$out/shift.json" ;;
    fast)
      export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
      timeout 150 python3 -m benchmarks.shift --seeds 5 --batch 512 --out "$out/shift.json"
      timeout 330 python3 -m benchmarks.update --methods dear --seeds 5 --batch 512 --iters 20 \
        --seed-axis loop --dtypes bfloat16 --shift-impls pad_slice gather one_hot \
        --out "$out/update_shift.json"
      best=$(python3 -c "import json; rows = json.load(open('$out/update_shift.json'))['rows']; \
print(min(rows, key=lambda r: r['ms_per_seed_update'])['shift_impl'])" || echo pad_slice)
      echo "fastest shift_impl in the update: $best"
      pl="timeout 240 python3 -m benchmarks.profile_loop --config configs/walker_dear.py --seeds 5 --envs 16 --dtype bfloat16 --warmup-frames 2400 --log-every 800 --iterations 10 --set agent.shift_impl=$best"
      $pl --out "$out/profile_loop_dear_$best.json" > "$out/profile_loop_dear_$best.log" 2>&1
      XLA_FLAGS="${CB_FLAGS:-$ALL_CB}" $pl --out "$out/profile_loop_dear_${best}_cb.json" \
        > "$out/profile_loop_dear_${best}_cb.log" 2>&1
      grep -h -A8 "per iteration" "$out"/profile_loop_dear_"$best"*.log
      # For the runs that follow: `source /tmp/runs/fast.env` sets FAST_SHIFT, and XLA_FLAGS
      # where the loop ran faster with every op kind in command buffers.
      python3 - "$out/profile_loop_dear_$best.json" "$out/profile_loop_dear_${best}_cb.json" \
        "$best" "${CB_FLAGS:-$ALL_CB}" > "$runs/fast.env" <<'PY'
import json, statistics, sys
fps = []
for path in sys.argv[1:3]:
    try:
        fps.append(statistics.mean(json.load(open(path))["untraced_fps_rows"]))
    except (OSError, KeyError, ValueError, statistics.StatisticsError):
        fps.append(0.0)
print(f"export FAST_SHIFT={sys.argv[3]}  # loop frames/s: {fps[0]:.0f}; all command buffers {fps[1]:.0f}")
if fps[1] > 1.02 * fps[0]:
    print(f'export XLA_FLAGS="{sys.argv[4]}"')
PY
      cat "$runs/fast.env" ;;
    axes)
      export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
      u="python3 -m benchmarks.update --seeds 5 --batch 512 --iters 20 --dtypes bfloat16 --seed-axis loop hybrid"
      timeout 330 $u --methods dear drqv2 --drqv2-encoder plain --out "$out/update_axes.json"
      XLA_FLAGS="$CONV_FUSION" timeout 240 $u --methods dear --out "$out/update_axes_convfusion.json"
      XLA_FLAGS="$CONV_FUSION $ALL_CB" timeout 240 $u --methods dear \
        --out "$out/update_axes_convfusion_cb.json"
      timeout 200 python3 -m benchmarks.profile_update --method dear --batch 512 --seeds 5 \
        --seed-axis hybrid --dtype bfloat16 --top 40 --out "$out/profile_dear_hybrid.json" \
        > "$out/profile_dear_hybrid.log" 2>&1
      head -n 60 "$out/profile_dear_hybrid.log" ;;
    evaldev)
      # The evaluation's device (config eval_device) in the DrQ-v2 learning check's loop:
      # 3 seeds x 16 envs, bf16, 10 episodes per seed every 5,000 frames per seed, in the
      # background, in a process of its own (policy on the CPU, or on the GPU); and without.
      export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
      t="python3 -m benchmarks.train --config configs/walker_drqv2_paper.py --seeds 3 --envs 16 --dtype bfloat16 --backend cpu --warmup-frames 2400 --frames 15000 --log-every 2500 --eval-episodes 10 --skip split --set replay.disk=false"
      for d in ${EVAL_DEVICES:-cpu accelerator none}; do
        if [ "$d" = none ]; then flags=""; else flags="--eval-every 5000 --set eval_device=$d"; fi
        timeout 200 $t $flags --out "$out/train_eval_$d.json" > "$out/train_eval_$d.log" 2>&1
      done
      grep -h -B1 -A1 "End to end" "$out"/train_eval_*.log ;;
    envsweep)
      export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
      for e in ${ENVS:-4 8 16 32}; do
        timeout 200 python3 -m benchmarks.train --config configs/walker_dear.py --seeds 5 \
          --envs "$e" --dtype bfloat16 --backend cpu --warmup-frames 2400 --frames 6000 \
          --log-every 1200 --skip split --set replay.disk=false \
          --out "$out/train_envs_${e}_h100.json" > "$out/train_envs_$e.log" 2>&1
        echo "$e envs per seed: $(grep -h "End to end" "$out/train_envs_$e.log")"
      done ;;
    gpushare)
      # Does an evaluation's drawing slow training through the GPU? The learning check's loop
      # without evaluation, alone and beside benchmarks/render_load.py (30 observations every
      # 40 ms, 8 workers: an evaluation's drawing, in a process of its own).
      export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
      t="python3 -m benchmarks.train --config configs/walker_drqv2_paper.py --seeds 3 --envs 16 --dtype bfloat16 --backend cpu --warmup-frames 2400 --frames 15000 --log-every 2500 --skip split --set replay.disk=false"
      timeout 200 $t --out "$out/train_alone.json" > "$out/train_alone.log" 2>&1
      # The load outlasts the training's measured span (it ends ~80-100 s after the start).
      timeout 200 python3 -m benchmarks.render_load --seconds 120 --out "$out/render_load.json" \
        > "$out/render_load.log" 2>&1 &
      timeout 200 $t --out "$out/train_beside_render.json" > "$out/train_beside_render.log" 2>&1
      wait
      grep -h "End to end" "$out"/train_alone.log "$out"/train_beside_render.log
      cat "$out/render_load.log" ;;
    pl)
      export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
      c=$1 n=$2 a=$3 f=$4; shift 4
      name=profile_loop_$(basename "$c" .py)_${n}x16_${a}$([ "$f" = cf ] && echo _cf)
      name=$name${PL_SET:+_${PL_SET##*=}}
      XLA_FLAGS="$([ "$f" = cf ] && echo "$CONV_FUSION")" timeout 290 python3 -m \
        benchmarks.profile_loop --config "$c" --seeds "$n" --envs 16 --dtype bfloat16 \
        --warmup-frames 2400 --log-every 800 --iterations 10 --set "agent.seed_axis=$a" \
        ${PL_SET:+--set "$PL_SET"} --out "$out/$name.json" > "$out/$name.log" 2>&1
      grep -h -A8 "per iteration" "$out/$name.log" ;;
    dispatch)
      # benchmarks/dispatch.py under XLA's defaults, its conv fusion, and without autotuning
      # (cuDNN's heuristic algorithms); then the DEAR bf16 update without autotuning.
      timeout 150 python3 -m benchmarks.dispatch --out "$out/dispatch.json"
      XLA_FLAGS="$CONV_FUSION" timeout 150 python3 -m benchmarks.dispatch \
        --out "$out/dispatch_cf.json"
      XLA_FLAGS="$NO_AUTOTUNE" timeout 150 python3 -m benchmarks.dispatch \
        --out "$out/dispatch_no_autotune.json"
      XLA_FLAGS="$NO_AUTOTUNE" timeout 200 python3 -m benchmarks.update --methods dear --seeds 5 \
        --batch 512 --iters 20 --dtypes bfloat16 --seed-axis hybrid \
        --out "$out/update_no_autotune.json" ;;
    pallas)
      export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
      timeout 240 python3 -m benchmarks.wgrad --out "$out/wgrad.json"
      python3 - "$out/wgrad.json" <<'PY'
import json, pathlib, re, sys
rows = [r for r in json.load(open(sys.argv[1]))["rows"] if r["variant"].startswith("pallas")]
best = min((r for r in rows if "ms_per_call" in r), key=lambda r: r["ms_per_call"])
images, warps = map(int, re.findall(r"\d+", best["variant"]))
p = pathlib.Path("dear_jax/wgrad.py")
text = re.sub(r"(?m)^IMAGES = \d+", f"IMAGES = {images}", p.read_text())
p.write_text(re.sub(r"(?m)^NUM_WARPS = \d+", f"NUM_WARPS = {warps}", text))
print(f"wgrad defaults in this tree: IMAGES={images} NUM_WARPS={warps}")
PY
      timeout 300 python3 -m benchmarks.update --methods dear drqv2 --drqv2-encoder plain \
        --seeds 5 --batch 512 --iters 20 --dtypes bfloat16 --seed-axis hybrid \
        --filter-gradients cudnn pallas --out "$out/update_pallas.json" ;;
    wideconv) set -- wcsweep wcupdate "$@" ;;
    wcsweep)
      # One or more sweeps of dear_jax/wideconv.py's settings, ';'-separated in $WC_SWEEPS, each
      # "PASS:NAME=v1,v2 NAME=..." (PASS forward or forward_backward: what picks the fastest).
      # Each sweep times the tree's current settings too, and writes its fastest into the tree,
      # so a later sweep starts from an earlier one's choice.
      export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
      IFS=';' read -ra sweeps <<< "${WC_SWEEPS:-forward_backward:BLOCK=64,128 NUM_WARPS=2,4}"
      n=0
      for sweep in "${sweeps[@]}"; do
        pass_=${sweep%%:*}; n=$((n + 1))
        # shellcheck disable=SC2086  # the grid's words
        timeout 400 python3 -m benchmarks.wideconv --passes "$pass_" --grid ${sweep#*:} \
          --out "$out/wideconv_sweep$n.json" > "$out/wideconv_sweep$n.log" 2>&1
        grep "^|" "$out/wideconv_sweep$n.log"
        python3 -m benchmarks.wideconv --pick "$out/wideconv_sweep$n.json" --by "$pass_"
      done
      cp dear_jax/wideconv.py "$out/wideconv_chosen.py" ;;
    wcupdate)
      # The update, the loop and the profile with the tree's wideconv settings.
      export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
      timeout 300 python3 -m benchmarks.update --methods dear drqv2 --drqv2-encoder plain \
        --seeds 5 --batch 512 --iters 20 --dtypes bfloat16 --seed-axis hybrid \
        --conv-stacks xla pallas --out "$out/update_wideconv.json"
      timeout 200 python3 -m benchmarks.train --config configs/walker_dear.py --seeds 5 \
        --envs 16 --dtype bfloat16 --backend cpu --warmup-frames 2400 --frames 6000 \
        --log-every 1200 --skip split --set replay.disk=false --set agent.conv_stack=pallas \
        --out "$out/train_dear_wideconv.json" > "$out/train_dear_wideconv.log" 2>&1
      grep -h "End to end" "$out/train_dear_wideconv.log"
      timeout 150 python3 -m benchmarks.profile_update --method dear --batch 512 --seeds 5 \
        --seed-axis hybrid --dtype bfloat16 --conv-stack pallas --hlo-out "$out/profile_dear_wideconv.hlo" \
        --out "$out/profile_dear_wideconv.json" > "$out/profile_dear_wideconv.log" 2>&1
      head -n 40 "$out/profile_dear_wideconv.log" ;;
    loop)
      export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
      b=${BACKEND:-config}
      pl="timeout 270 python3 -m benchmarks.profile_loop --envs 16 --dtype bfloat16 --warmup-frames 2400 --log-every 800 --iterations 20 ${BACKEND:+--backend $BACKEND}"
      $pl --config configs/walker_drqv2_paper.py --seeds 3 \
        --out "$out/profile_loop_drqv2_$b.json" > "$out/profile_loop_drqv2_$b.log" 2>&1
      $pl --config configs/walker_dear.py --seeds 5 \
        --out "$out/profile_loop_dear_$b.json" > "$out/profile_loop_dear_$b.log" 2>&1
      grep -h -A8 "per iteration" "$out"/profile_loop_*_$b.log ;;
    evalcost|evalload)
      # One call each: alone, then beside a training run (each near a call's 10 minutes).
      e="python3 -m benchmarks.evaluation --steps 100 --reps 3 --placements accelerator:default accelerator:cpu cpu:cpu --physics-threads 1 8"
      if [ $stage = evalcost ]; then name=evaluation_alone; load=; t=300
      else name=evaluation_beside_train; load=--load; t=500; fi
      timeout $t $e $load --out "$out/$name.json" > "$out/$name.log" 2>&1
      tail -n 10 "$out/$name.log" ;;
    evalrun)
      # One evaluation of the learning check as a run's evaluation process runs it: the policy on
      # the GPU, the env's arrays on XLA:CPU, 8 physics threads, whole episodes, videos written.
      timeout 200 python3 -m benchmarks.evaluation --steps 500 --reps 2 --placements accelerator:cpu \
        --physics-threads 8 --video --out "$out/evaluation_run.json" > "$out/evaluation_run.log" 2>&1
      tail -n 5 "$out/evaluation_run.log" ;;
    torch)
      timeout 300 python3 -m benchmarks.torch_reference update --methods dear --batch 512 \
        --iters 20 --variants eager best --out "$out/torch.json" ;;
    scaling)
      timeout 590 python3 -m benchmarks.scaling --config configs/walker_dear.py --devices 1 2 \
        --seeds-per-device 5 --envs 8 --warmup-frames 2400 --frames 6400 --log-every 1600 \
        --out "$out/scaling.json" > "$out/scaling.log" 2>&1
      grep -v warp "$out/scaling.log" | tail -n 8 ;;
    wait) sleep "$1"; shift ;;
    finish)
      end=$((SECONDS + $1)); shift
      while pgrep -f '^python3 run.py' > /dev/null && [ $SECONDS -lt $end ]; do sleep 2; done
      set -- stop collect "$@" ;;
  esac
  echo "=== $stage done rc=$? $(date +%T)"
done
