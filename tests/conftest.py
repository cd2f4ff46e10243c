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

if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="dear_jax_tests_jax_cache_")
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")

# XLA:CPU's fusion emitters off in every process of the test run (the tests' child processes
# inherit XLA_FLAGS; those of test_sharding.py and test_multihost.py set it themselves): in one
# process on a 2-core machine, tests/test_update.py took 211 s against 299 s with them on. The
# persistent cache's keys include XLA_FLAGS but for the device count, so the children share the
# workers' compiled programs. (Off, jax.random compiles more slowly: ~10 s for an image-sized
# draw; the tests draw their inputs with NumPy.)
if "--xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_cpu_use_fusion_emitters=false"
    os.environ["XLA_FLAGS"] = flags.strip()

SLOWEST_FIRST = (
    "test_sharding.py",
    "test_run.py",
    "test_update.py",
    "test_multihost.py",
    "test_networks.py",
    "test_evaluator.py",
    "test_kitchen.py",
    "test_wideconv.py",
    "test_physics.py",
    "test_envs.py",
    "test_render.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(SLOWEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: files stay whole
