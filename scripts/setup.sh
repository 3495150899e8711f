#!/usr/bin/env bash
# Idempotent set-up on a fresh Debian machine: Python with venv/pip, Mesa for headless OpenGL, a
# virtualenv at .venv, the project and its dev tools, then the optional benchmark peer;
# redis-server and nginx (the shared-cache and deployment tests), chromium and node/npm for the
# browser viewer and its tests, and three.js from npm (`npm ci`). Safe to run again; it skips
# what is already there.
#
# `setup.sh python`: only Python and .venv (all `pvs warmup` needs); `setup.sh system`: only the
# rest (the Debian packages and three.js), which the test command installs while the kernels
# compile. No argument: both, in that order.
set -euo pipefail
cd "$(dirname "$0")/.."
PART=${1:-all}
case "$PART" in
  all|python|system) ;;
  *) echo "usage: scripts/setup.sh [python|system]" >&2; exit 2 ;;
esac

PY=${PYTHON:-python3}
have_venv() { [ -x .venv/bin/python ] && .venv/bin/python -m pip --version >/dev/null 2>&1; }

# PVS_SETUP_RUNTIME=1 (the Docker image) installs what the server needs to run, not what only
# the tests and benchmarks start (they start their own redis-server and nginx on loopback ports;
# no system service is relied on), nor the dev tools.
RUNTIME=${PVS_SETUP_RUNTIME:-0}
apt_install() {
  [ $# -gt 0 ] || return 0
  echo "[setup] installing Debian packages: $*"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}

system_part() {
  local pkgs need_apt=() pkg
  pkgs=(libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libxrender1 libosmesa6)
  [ "$RUNTIME" = 1 ] || pkgs+=(redis-server nginx-light)
  for pkg in "${pkgs[@]}"; do
    dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
  done
  # The viewer's browser tests drive Debian's chromium through its driver (selenium); node and
  # npm install three.js, which the server serves to the viewer's page (package-lock.json; the
  # Docker image takes it from a node stage instead).
  if [ "$RUNTIME" != 1 ]; then
    for pkg in chromium chromium-driver; do
      dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
    done
    command -v npm >/dev/null 2>&1 || need_apt+=(nodejs npm)
  fi
  apt_install "${need_apt[@]}"
  # three.js for the browser viewer, exactly as package-lock.json pins it (node_modules/ is not
  # in the repository; the server serves its build folder at /viewer/vendor/).
  local npm_stamp=node_modules/.pvs-installed
  if [ "$RUNTIME" != 1 ] && { [ ! -f "$npm_stamp" ] || [ package-lock.json -nt "$npm_stamp" ]; }; then
    echo "[setup] installing three.js (npm ci)"
    npm ci --no-audit --no-fund --loglevel=error
    touch "$npm_stamp"
  fi
}

if [ "$PART" = system ]; then
  system_part
  exit 0
fi

# Python itself, and what `python3 -m venv` needs: Debian splits venv/ensurepip (python3-venv)
# and pip (python3-pip) out of python3, so a fresh machine fails at `-m venv` without them.
need_apt=()
if ! command -v "$PY" >/dev/null 2>&1; then
  need_apt+=(python3 python3-venv python3-pip)
  PY=python3
elif ! have_venv; then
  { "$PY" -m venv --help && "$PY" -c "import ensurepip"; } >/dev/null 2>&1 \
    || need_apt+=(python3-venv)
  "$PY" -m pip --version >/dev/null 2>&1 || need_apt+=(python3-pip)
fi
apt_install "${need_apt[@]}"

"$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
  || { echo "[setup] Python >= 3.11 is needed; $PY is $("$PY" -V 2>&1)" >&2; exit 1; }

# A venv left without pip (created before python3-venv was there) is rebuilt, not reused.
if ! have_venv; then
  echo "[setup] creating .venv"
  "$PY" -m venv --clear .venv
fi
stamp=.venv/.pvs-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "[setup] installing the project into .venv"
  # uv resolves and installs in seconds where pip takes a minute; it goes into the venv itself.
  .venv/bin/python -m pip install -q --upgrade pip uv
  uvpip=(.venv/bin/python -m uv pip install -q --python .venv/bin/python)
  if [ "$RUNTIME" = 1 ]; then extras=""; else extras="[dev]"; fi
  # pyrender pins PyOpenGL 3.1.0 whose OSMesa binding is broken: the override takes the working
  # one (scripts/overrides.txt).
  "${uvpip[@]}" -e ".$extras" --override scripts/overrides.txt
  # The `bench` extra (embreex, the benchmark's ray-caster peer) has no wheel on some platforms;
  # the benchmark skips that peer without it (benchmarks.peers.available), so its failure must
  # not fail the set-up.
  if [ "$RUNTIME" != 1 ]; then
    if ! "${uvpip[@]}" -e ".[bench]" --override scripts/overrides.txt \
        >.venv/bench-install.log 2>&1; then
      echo "[setup] optional bench extra not installed (see .venv/bench-install.log); the benchmark skips its peer"
    fi
  fi
  touch "$stamp"
fi

[ "$PART" = python ] || system_part
