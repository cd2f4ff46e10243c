"""The slowest test files first: xdist's workers (pyproject.toml: --dist loadfile, each file on
one worker, --no-loadscope-reorder) take the files in this order, so that no long file starts
last on one worker while the other has nothing left. Measured on a 2-core machine, slowest
first; the other files follow in their usual order.

Compiled programs are shared through JAX's persistent compilation cache, in a folder made for
this test session (before jax is imported, so that xdist's workers and the tests' child
processes inherit it) and removed at its end: many tests compile the same tiny update, acting
and evaluation programs, in their own trainings or processes. A JAX_COMPILATION_CACHE_DIR set
by the caller is used as it is."""

import atexit
import os
import shutil
import tempfile

# Every test draws with EGL (a GPU's, or Mesa's on CPU-only machines), whichever module imports
# mujoco first: the README's test command works without exporting it.
os.environ.setdefault("MUJOCO_GL", "egl")

if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="dear_jax_tests_jax_cache_")
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")

# XLA:CPU flags for every process of the test run (the tests' child processes inherit
# XLA_FLAGS; those of test_sharding.py and test_multihost.py add their device count to them).
# The tests' programs are small and run a few times, so compiling them is most of the suite's
# time; on a 2-core machine:
# - fusion emitters off: tests/test_update.py took 211 s against 299 s with them on (and a
#   seed's code is then the same in a 1-seed and a 2-seed program, which test_sharding.py
#   relies on; jax.random compiles more slowly, so the tests draw their inputs with NumPy);
# - LLVM at optimisation level 0: test_vmapped_seeds_every_method[drqv2] took 12 s against
#   22 s at the default level;
# - each program's LLVM module compiled whole, not split into parts compiled on parallel
#   threads: tests/test_update.py took 111 s of CPU (103 s) against 117-152 s (109-137 s) split,
#   the same programs otherwise.
# The persistent cache's keys include XLA_FLAGS but for the device count, so the children share
# the workers' compiled programs.
TEST_XLA_FLAGS = (
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_backend_optimization_level=0",
    "--xla_cpu_parallel_codegen_split_count=1",
)
_flags = os.environ.get("XLA_FLAGS", "")
os.environ["XLA_FLAGS"] = " ".join(
    [_flags, *(f for f in TEST_XLA_FLAGS if f.split("=")[0] not in _flags)]
).strip()


SLOWEST_FIRST = (
    "test_sharding.py",
    "test_run.py",
    "test_update.py",
    "test_kitchen.py",
    "test_multihost.py",
    "test_wideconv.py",
    "test_physics.py",
    "test_networks.py",
    "test_evaluator.py",
    "test_render.py",
    "test_replay.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(SLOWEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: files stay whole
