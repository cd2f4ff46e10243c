#!/usr/bin/env bash
# Measurements and long runs on a GPU machine without network access, in stages:
#
#   bash benchmarks/device.sh STAGE [ARGS] [STAGE [ARGS]]...
#
#   scaling N...        benchmarks/scaling.py on N... GPUs (DEAR walker-walk, 1 and 3 seeds per
#                       GPU, bf16, 16 envs per seed, the Pallas conv stacks) -> $OUT/scaling.json
#   multihost           benchmarks/multihost.py: 2 processes on GPUs 0 and 1 (jax.distributed,
#                       a local coordinator), stopped by SIGTERM and resumed, against one
#                       process on both GPUs -> $OUT/multihost.json
#   bench NAME ARGS...  `python3 -m benchmarks.NAME ARGS...` (takes the rest of the line: last
#                       stage), e.g. a figure's command from benchmarks/RESULTS.md with
#                       `--out $OUT/NAME.json`
#   gpu N               the bench stages after it run on GPU number N alone, pinned to that
#                       GPU's share of the cores (as `start` pins a run), e.g. to measure on
#                       one GPU while runs train on the others
#   start NAME GPU ARGS  a detached `run.py ARGS --workdir runs/NAME` on GPU number GPU, or the
#                       GPUs of a list ("0,1"; "all": every GPU), its console in runs/NAME.out;
#                       it outlives this call. ARGS are the words that start with `--` (write
#                       `--config=FILE`). A run on some GPUs is pinned to their shares of the
#                       cores (GPU i of G: the i-th of G equal blocks), so runs side by side
#                       don't share cores. Several runs
#                       on one GPU: give each a share of its memory, e.g.
#                       `XLA_PYTHON_CLIENT_MEM_FRACTION=0.22 bash benchmarks/device.sh start ...`
#                       CORES=LIST (taskset's syntax, e.g. 0-15,48-52) pins the run there instead.
#                       A run given one GPU more than it trains on evaluates on the last one
#                       (evaluator.spare_device) and draws its frames there (env.render.gpus
#                       "auto"; several runs sharing it for that, not measured: give
#                       `--config.env.render.gpus=0` to draw beside the updates); runs sharing
#                       it start with XLA_PYTHON_CLIENT_PREALLOCATE=false, or each would claim
#                       most of its memory
#   grid ARGS...        the paper's grid's missing seed-runs as a detached queue, one per GPU at a
#                       time (`python -m dear_jax.grid ARGS --root runs`, e.g. `grid results/*/*/
#                       --set agent.compute_dtype=bfloat16 --set replay.disk=False`), its log in
#                       runs/grid.out; `wait`, `stop` and `collect` treat it as a run (SIGTERM
#                       reaches its runs). It takes the rest of the line: last stage. Two queues
#                       side by side: give each its GPUs (`--gpus 0,1`), their cores, the second a
#                       name, and tasks of their own (neither sees the other's cells):
#                       `CORES=0-31 bash benchmarks/device.sh grid ... --gpus 0,1`, then
#                       `GRID=ablations CORES=32-63 bash benchmarks/device.sh grid ... --gpus 2,3`
#                       (runs/ablations.out)
#   wait S              sleep up to S seconds while runs train, printing their last log lines;
#                       returns early once none is running
#   stop [NAME...]      SIGTERM the runs named (every run `start` began if none; each saves a
#                       checkpoint and its summary), wait for them
#   after NAME          wait until run NAME has ended, e.g. `after walker_s0 gpu 0 bench ...`
#                       to measure on its GPU once it is free
#   collect             the runs' logs and summaries (no checkpoints, replay or videos) ->
#                       $OUT/runs.tar.gz
#   pack                every other file under $OUT moved into $OUT/results.tar.gz (one file to
#                       copy back, however many JSON the bench stages wrote)
#
# What the machine must be given (it has CUDA jax, flax, optax, orbax, opencv, matplotlib):
# wheels in .whl/ and EGL loaders in .gl/ (any folder of wheels `pip install --no-index` takes;
# the pinned packages it lacks: mujoco, mujoco-mjx, ml-collections, tensorboardX, and for the
# kitchen's simplified meshes fast-simplification),
# dm_control's suite models in .dmc/ (benchmarks/device_dmc.sh); for env.render.gpus "cpu", Mesa's
# EGL and llvmpipe in .mesa/ (benchmarks/device_mesa.sh). The tree sent there has no
# .git: export DEAR_JAX_COMMIT=<commit> so JSON and summaries name the code's commit. JAX's
# compilation cache is $JAX_COMPILATION_CACHE_DIR (default /tmp/jax_cache).
set -uo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-/tmp/out}
mkdir -p "$out" runs

if [ -d .gl ]; then for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; fi
if [ -d .mesa ]; then  # benchmarks/device_mesa.sh: each package one of whose libraries is missing
  for f in .mesa/*/*.deb; do  # by the names the loader asks for: libffi.so.8, swrast_dri.so
    for lib in $(dpkg-deb -c "$f" | awk '$6 ~ /\.so(\.[0-9]+)?$/ {print substr($6, 2)}'); do
      [ -e "$lib" ] || { dpkg -x "$f" /; echo "unpacked $(basename "$f")"; break; }
    done
  done
  ldconfig
fi
if [ -d .whl ] && [ ! -d /tmp/site ]; then
  python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl || exit 1
fi
kitchen=.dmc/gymnasium_robotics  # the kitchen's scene, packed by benchmarks/device_dmc.sh
if [ -f $kitchen/kitchen_franka.tar.gz ] && [ ! -d $kitchen/envs/assets/kitchen_franka ]; then
  mkdir -p $kitchen/envs/assets && tar -C $kitchen/envs/assets -xzf $kitchen/kitchen_franka.tar.gz
fi
export PYTHONPATH=/tmp/site:$PWD/.dmc:$PWD MUJOCO_GL=egl PYTHONUNBUFFERED=1
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-/tmp/jax_cache}
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | sed 's/^/gpu: /'

alive() { [ -f "runs/$1.pid" ] && kill -0 "$(cat "runs/$1.pid")" 2>/dev/null; }
# The runs `start` began (by their pid files, never by a command-line pattern, which would also
# match the shell of a command that names it)
started() { for f in runs/*.pid; do [ -f "$f" ] && basename "$f" .pid; done; }
running() { for n in $(started); do alive "$n" && return 0; done; return 1; }
gpus() { nvidia-smi --query-gpu=index --format=csv,noheader | wc -l; }
cores_of() {  # the cores of GPU $1's share of the machine: "first-last"
  local share=$(($(nproc) / $(gpus)))
  echo "$(($1 * share))-$(($1 * share + share - 1))"
}
bench_pin=()

while [ $# -gt 0 ]; do
  stage=$1; shift
  case $stage in
    scaling)
      devices=()
      while [ $# -gt 0 ] && [[ $1 =~ ^[0-9]+$ ]]; do devices+=("$1"); shift; done
      [ ${#devices[@]} -gt 0 ] || devices=(1 2)
      python3 -m benchmarks.scaling --devices "${devices[@]}" --out "$out/scaling.json"
      ;;
    multihost)
      python3 -m benchmarks.multihost --out "$out/multihost.json"
      ;;
    gpu)
      [[ $1 =~ ^[0-9]+$ ]] || { echo "gpu takes a GPU number, got '$1'" >&2; exit 2; }
      bench_pin=(env CUDA_VISIBLE_DEVICES="$1" taskset -c "$(cores_of "$1")"); shift
      ;;
    bench)
      name=$1; shift
      "${bench_pin[@]}" python3 -m "benchmarks.$name" "$@"
      set --
      ;;
    start)
      name=$1 gpu=$2; shift 2
      [[ $gpu =~ ^([0-9]+(,[0-9]+)*|all)$ ]] || { echo "start takes a GPU number, a list such as 0,1, or all; got '$gpu'" >&2; exit 2; }
      args=()
      while [ $# -gt 0 ] && [[ $1 == --* ]]; do args+=("$1"); shift; done
      visible=$([ "$gpu" = all ] && nvidia-smi --query-gpu=index --format=csv,noheader | paste -sd, || echo "$gpu")
      pin=()
      [ "$gpu" != all ] && pin=(taskset -c "$(for g in ${gpu//,/ }; do cores_of "$g"; done | paste -sd,)")
      [ -n "${CORES:-}" ] && pin=(taskset -c "$CORES")
      CUDA_VISIBLE_DEVICES=$visible setsid nohup "${pin[@]}" python3 run.py "${args[@]}" --workdir "runs/$name" \
        >"runs/$name.out" 2>&1 </dev/null &
      echo $! >"runs/$name.pid"
      echo "started runs/$name on GPU $visible ${pin[*]}: run.py ${args[*]}"
      ;;
    grid)
      name=${GRID:-grid} pin=()
      [[ $name =~ ^[A-Za-z0-9_.-]+$ ]] || { echo "GRID names a queue (letters, digits, _.-), got '$name'" >&2; exit 2; }
      alive "$name" && { echo "a queue named $name is running: give another GRID=NAME" >&2; exit 2; }
      [ -n "${CORES:-}" ] && pin=(taskset -c "$CORES")  # the cores its jobs share out
      setsid nohup "${pin[@]}" python3 -m dear_jax.grid "$@" --root runs >"runs/$name.out" 2>&1 </dev/null &
      echo $! >"runs/$name.pid"
      echo "started the grid's queue runs/$name: python -m dear_jax.grid $* --root runs"
      set --
      ;;
    wait)
      end=$((SECONDS + $1)); shift
      while running && [ $SECONDS -lt $end ]; do sleep 5; done
      for f in runs/*.out; do [ -f "$f" ] && echo "$f: $(tail -n 1 "$f")"; done
      ;;
    stop)
      names=()
      while [ $# -gt 0 ] && [ -f "runs/$1.pid" ]; do names+=("$1"); shift; done
      [ ${#names[@]} -gt 0 ] || names=($(started))
      for n in "${names[@]}"; do alive "$n" && kill -TERM "$(cat "runs/$n.pid")"; done
      for n in "${names[@]}"; do
        for _ in $(seq 120); do alive "$n" || break; sleep 1; done
        echo "runs/$n: $(tail -n 1 "runs/$n.out")"
      done
      ;;
    after)
      name=$1; shift
      [ -f "runs/$name.pid" ] || { echo "after takes the name of a started run, got '$name'" >&2; exit 2; }
      while alive "$name"; do sleep 3; done
      ;;
    collect)
      tar -czf "$out/runs.tar.gz" --exclude='checkpoints*' --exclude=replay --exclude=videos \
        --exclude='*.lock' --exclude='*.pid' runs
      ls -la "$out"
      ;;
    pack)
      (cd "$out" && find . -type f ! -name runs.tar.gz ! -name results.tar.gz -print0 |
        tar -czf results.tar.gz --null -T - --remove-files && tar -tzf results.tar.gz)
      ;;
    *)
      echo "unknown stage '$stage'; valid: scaling multihost gpu bench start grid wait stop after collect pack" >&2
      exit 2
      ;;
  esac
done
