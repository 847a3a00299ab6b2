#!/usr/bin/env bash
# Install everything the test suite needs on a fresh Debian/Ubuntu machine, then the project
# (with its test extras) into ./.venv. Safe to run again: it installs only what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

# Debian packages: C++ toolchains and tools the firmware and tools tests drive.
APT_PACKAGES=(
  make g++ clang libclang-rt-14-dev doctest-dev          # host firmware build, sanitizers, libFuzzer
  gcc-arm-none-eabi libnewlib-arm-none-eabi libstdc++-arm-none-eabi-newlib  # Cortex-M4F build
  qemu-system-arm                                         # runs the M4 unit tests
  ffmpeg chromium socat                                   # third-party stream clients, ptys
  libcairo2                                               # cairosvg: make-body --pdf
)
missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  echo "install.sh: installing Debian packages: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[test]'
.venv/bin/cubetrack compile >/dev/null   # numba's kernels into its cache now, not on the first tracker's start

# The official Foxglove WebSocket client library (npm; versions pinned in its package-lock.json),
# which tests/e2e/test_outputs.py runs against the live server. Without npm that test is skipped.
if command -v npm >/dev/null; then
  [ -d tests/e2e/foxglove_client/node_modules/@foxglove/ws-protocol ] ||
    npm ci --prefix tests/e2e/foxglove_client --no-audit --no-fund --loglevel=error ||
    echo "install.sh: npm ci failed: the official Foxglove client test will be skipped"
else
  echo "install.sh: npm not found: the official Foxglove client test will be skipped"
fi
