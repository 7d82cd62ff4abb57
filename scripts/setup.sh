#!/usr/bin/env bash
# Installs everything workbench needs on a fresh Debian 12 machine, skipping what is already there:
# the Debian packages (OSMesa for offscreen depth, libusb for open3d, Chromium for the browser tests) and a
# Python 3.11 virtual environment in .venv (with the optional Ray engine and MuJoCo physics, so that CI tests them). Sourced by scripts/demo.sh and scripts/test.sh.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

apt_packages=(libosmesa6 libegl1 libgl1 libusb-1.0-0)
[ "${WORKBENCH_BROWSER:-1}" = 1 ] && apt_packages+=(chromium fonts-liberation)
missing=()
for p in "${apt_packages[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${missing[*]}" >&2
  sudo_cmd=""
  [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

python_bin="$(command -v python3.11 || command -v python3)"
if ! "$python_bin" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
  echo "setup: workbench needs Python 3.11 (pybullet 3.2.7 has no wheels for newer versions); found $("$python_bin" --version)" >&2
  exit 1
fi
stamp=".venv/.installed-$(sha1sum pyproject.toml | cut -c1-12)"
if [ ! -f "$stamp" ]; then
  echo "setup: creating .venv and installing workbench (about a minute)" >&2
  "$python_bin" -m venv .venv
  .venv/bin/pip install -q --disable-pip-version-check -e '.[test,ray,mujoco]'
  # Second call on purpose: pyrender pins PyOpenGL 3.1.0, whose OSMesa binding is broken.
  .venv/bin/pip install -q --disable-pip-version-check 'PyOpenGL==3.1.10' 2>&1 | grep -v "dependency conflicts\|requires PyOpenGL" >&2 || true
  rm -f .venv/.installed-*
  touch "$stamp"
fi
