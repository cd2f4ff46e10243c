#!/usr/bin/env bash
# Runs benchmarks/envs.py on the GPU machine in several processes (XLA flags differ per
# process), each with its own time limit, results as JSON under $OUT. Usage: bash this [stage...]
# Stages: gl physics render env unroll cmdbuf accurate variants reference
set -u
out=${OUT:-/tmp/out}
mkdir -p "$out"
export JAX_COMPILATION_CACHE_DIR=/tmp/jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
b="python3 -m benchmarks.envs --seeds 5"
for stage in "$@"; do
  echo "=== $stage $(date +%T)"
  case $stage in
    gl) timeout 60 python3 -c "
import envs.render as r, mujoco, functools
from envs import dmc
t = dmc.TASKS['walker-walk']; m = t.render_model()
with r.RenderPool(functools.partial(dmc.render_model_fn, t.name), camera=0, agent_geom_ids=t.agent_geom_ids(m), floor_geom_ids=t.floor_geom_ids(m), settings=r.RenderSettings(num_workers=1)) as p: print(p.gl_info())
" ;;
    physics) timeout 200 $b --what physics --label "default solver" --out "$out/physics.json" ;;
    render) timeout 120 $b --what render --workers 8 16 --calls 30 --out "$out/render.json" ;;
    env) timeout 120 $b --what env --envs 8 --workers 8 --steps 30 --out "$out/env.json" ;;
    unroll) timeout 200 $b --what physics --unroll 10 --label "unroll 10" --out "$out/physics_unroll10.json" ;;
    cmdbuf) XLA_FLAGS="--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL" timeout 150 $b --what physics --label "command buffers +WHILE,+CONDITIONAL" --out "$out/physics_cmdbuf.json" ;;
    accurate) timeout 150 $b --what physics --iterations 6 --ls-iterations 10 --label "solver (6, 10)" --out "$out/physics_6_10.json" ;;
    variants)
      v="timeout 70 $b --what physics --envs 8 --steps 30"
      $v --iterations 3 --label "(3, 5)" --out "$out/v_3_5.json"
      $v --ls-iterations 3 --label "(4, 3)" --out "$out/v_4_3.json"
      $v --no-euler-damping --label "(4, 5) no Euler damping" --out "$out/v_nodamp.json"
      $v --solver cg --label "(4, 5) CG" --out "$out/v_cg.json"
      $v --iterations 3 --ls-iterations 3 --no-euler-damping --label "(3, 3) no Euler damping" --out "$out/v_3_3_nodamp.json" ;;
    reference) timeout 90 $b --what physics --envs 8 --iterations 100 --ls-iterations 50 --steps 10 --label "dm_control solver (100, 50)" --out "$out/physics_reference.json" ;;
  esac
  echo "=== $stage done rc=$? $(date +%T)"
done
