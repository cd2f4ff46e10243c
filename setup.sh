#!/usr/bin/env bash
# One-time set-up on a fresh Debian/Ubuntu machine: EGL/Mesa for headless MuJoCo rendering,
# then this package with its pinned Python dependencies.
set -euo pipefail
cd "$(dirname "$0")"
if ! ldconfig -p | grep -q 'libEGL_mesa\|libEGL_nvidia'; then
  sudo=""; [ "$(id -u)" -eq 0 ] || sudo="sudo"
  $sudo apt-get update -q
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -q libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libglx-mesa0
fi
python3 -m pip install -q -e ".[dev]"
