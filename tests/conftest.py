"""The slowest test files first: xdist's workers (pyproject.toml: --dist loadfile, each file on
one worker, --no-loadscope-reorder) take the files in this order, so that no long file starts
last on one worker while the other has nothing left. Measured on a 2-core machine, slowest
first; the other files follow in their usual order."""

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
