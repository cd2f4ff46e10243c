#!/usr/bin/env bash
# Mesa's EGL and software rasteriser (llvmpipe) for a GPU machine without network access, so
# that render workers can draw on its CPU cores (env.render.gpus "cpu"): downloads the Debian
# packages Mesa's EGL needs into .mesa/llvm/ (LLVM, 23 MB) and .mesa/rest/ (27 MB), git-ignored.
# What one call may carry is limited: carry each folder in a call of its own, before the calls
# that need it, on the same machine. benchmarks/device.sh unpacks into / each package one of
# whose libraries the machine lacks, as it does .gl/.
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
rm -rf .mesa && mkdir -p .mesa/llvm .mesa/rest /tmp/apt-amd64/partial
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/apt-amd64'
apt-get $o update >/dev/null
# libegl-mesa0 / libgl1-mesa-dri and what they link that a CUDA image may not have, by this
# machine's package lists (Debian 12: Mesa 22.3, LLVM 15; other releases name other versions).
# Unpacked on Ubuntu 24.04 (an H200 machine, 2026-11-30): llvmpipe drew there.
(cd .mesa/llvm && apt-get -q $o download libllvm15)
(cd .mesa/rest && apt-get -q $o download libegl-mesa0 libgl1-mesa-dri libglapi-mesa libgbm1 \
  libz3-4 libdrm2 libdrm-amdgpu1 libdrm-intel1 libdrm-nouveau2 libdrm-radeon1 libpciaccess0 \
  libelf1 libedit2 libbsd0 libmd0 libsensors5 libwayland-client0 libwayland-server0 libx11-xcb1 \
  libxcb1 libxau6 libxdmcp6 libxcb-dri2-0 libxcb-dri3-0 libxcb-present0 libxcb-randr0 \
  libxcb-sync1 libxcb-xfixes0 libxshmfence1 libxml2 libicu72 libffi8)
exclude=$(git rev-parse --git-path info/exclude)
grep -qx '/.mesa/' "$exclude" 2>/dev/null || echo '/.mesa/' >> "$exclude"
du -sh .mesa
