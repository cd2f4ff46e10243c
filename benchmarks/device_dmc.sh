#!/usr/bin/env bash
# The DMC tasks read their XML models from dm_control's `suite/` folder (envs/dmc.py). For a GPU
# machine without network access or dm_control, where its wheel (56 MB) is too large to send
# beside the others, this copies the installed package's suite models (XMLs
# and common assets, ~0.2 MB) into .dmc/dm_control/ (git-ignored), a package that
# `importlib.util.find_spec("dm_control")` finds: carry ".dmc" and put $PWD/.dmc on PYTHONPATH.
# Likewise the kitchen's scene (D4RL's, 15 MB) from gymnasium-robotics, which envs/kitchen.py
# finds the same way: packed as .dmc/gymnasium_robotics/kitchen_franka.tar.gz (11 MB: what a
# call may carry is limited), which benchmarks/device.sh unpacks in place.
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
src=$(python3 -c "import importlib.util as u; print(u.find_spec('dm_control').submodule_search_locations[0])")
rm -rf .dmc && mkdir -p .dmc/dm_control/suite
cp "$src"/suite/*.xml .dmc/dm_control/suite/
cp -r "$src"/suite/common .dmc/dm_control/suite/
kitchen=$(python3 -c "import importlib.util as u; s = u.find_spec('gymnasium_robotics'); print(s.submodule_search_locations[0] if s else '')")
if [ -n "$kitchen" ]; then
  mkdir -p .dmc/gymnasium_robotics
  tar -C "$kitchen/envs/assets" -czf .dmc/gymnasium_robotics/kitchen_franka.tar.gz kitchen_franka
else
  echo "gymnasium-robotics is not installed here: .dmc gets no kitchen scene" >&2
fi
find .dmc \( -name '*.py' -o -name __pycache__ \) -prune -exec rm -rf {} +
touch .dmc/dm_control/__init__.py
[ -d .dmc/gymnasium_robotics ] && touch .dmc/gymnasium_robotics/__init__.py
exclude=$(git rev-parse --git-path info/exclude)
grep -qx '/.dmc/' "$exclude" 2>/dev/null || echo '/.dmc/' >> "$exclude"
du -sh .dmc
