#!/usr/bin/env bash
# Idempotent set-up on a fresh Debian machine: Mesa for headless OpenGL, a virtualenv at .venv,
# the project and its dev tools. Safe to run again; it skips what is already there.
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
for pkg in libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libxrender1 libosmesa6; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
if [ ${#need_apt[@]} -gt 0 ]; then
  echo "[setup] installing Debian packages: ${need_apt[*]}"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need_apt[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv"
  "$PY" -m venv .venv
fi
stamp=.venv/.pvs-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "[setup] installing the project into .venv"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[dev,bench]"
  # pyrender pins PyOpenGL 3.1.0 whose OSMesa binding is broken; install the working one as a
  # separate step (asking for both at once makes pip fall back to an ancient pyrender).
  .venv/bin/python -m pip install -q "PyOpenGL==3.1.10"
  touch "$stamp"
fi
