#!/usr/bin/env bash
# One-time set-up on a fresh Debian/Ubuntu machine: EGL/Mesa for headless MuJoCo rendering and
# Python's venv module (apt, when missing), then a virtual environment .venv/ holding this package
# with its pinned dependencies and the test tools. Extras: SETUP_EXTRAS=dev,cuda ./setup.sh on a
# GPU machine. Afterwards: .venv/bin/python run.py ... (or `source .venv/bin/activate`).
set -euo pipefail
cd "$(dirname "$0")"
python3 -c 'import sys; sys.exit(sys.version_info < (3, 11))' || {
  echo "error: python3 is $(python3 -V 2>&1 | cut -d' ' -f2); the pinned jax, flax and mujoco need Python >= 3.11" >&2
  exit 1
}
packages=()
if ! ldconfig -p | grep -q 'libEGL_mesa\|libEGL_nvidia'; then
  packages+=(libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libglx-mesa0)
fi
if ! python3 -c "import ensurepip, venv" 2>/dev/null; then
  packages+=(python3-venv)  # Debian's python3 ships venv without ensurepip
fi
if [ ${#packages[@]} -gt 0 ]; then
  sudo=""; [ "$(id -u)" -eq 0 ] || sudo="sudo"
  $sudo apt-get update -q
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -q "${packages[@]}"
fi
[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install -q -e ".[${SETUP_EXTRAS:-dev}]"
echo "ready: .venv/bin/python run.py --config smoke; .venv/bin/python -m pytest -q"
