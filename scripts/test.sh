#!/usr/bin/env bash
# The test suite on a fresh machine: set up, lint, compile the kernels once, then pytest in
# PVS_TEST_WORKERS processes (default twice the cores, at most 8; real server on loopback, real
# WebSocket clients, headless pyrender). Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh python
source scripts/env.sh
# The Debian packages and three.js only the tests use (redis, nginx, chromium, node) install
# while the kernels compile, not before (apt and npm wait on the network, numba on the CPU).
system_log=$(mktemp)
bash scripts/setup.sh system >"$system_log" 2>&1 &
system_pid=$!
.venv/bin/ruff check .
# Compiled once here, the kernels load from the numba cache in every test process; otherwise
# each pytest worker compiles the ones it meets first, the same ones twice.
# Its report goes to a file tests/visibility/test_warmup.py reads instead of running it again.
export PVS_WARMUP_REPORT="$NUMBA_CACHE_DIR/warmup-report.txt"
mkdir -p "$NUMBA_CACHE_DIR"
.venv/bin/python -m pvs_cli warmup | tee "$PVS_WARMUP_REPORT"
if ! wait "$system_pid"; then
  cat "$system_log" >&2
  echo "[test] set-up of the system packages failed" >&2
  exit 1
fi
cat "$system_log"
rm -f "$system_log"
# loadgroup: tests marked with one xdist_group (a real scene's, a module's) share one worker,
# so what they build once per process (the kitchen, a scene's references, a server) is built
# once per run.
# Twice as many processes as cores: much of the suite waits on servers, browsers, sockets and
# child processes, and one process per core left the cores idle that long.
cores=$(nproc)
workers=${PVS_TEST_WORKERS:-$(( 2 * cores < 8 ? 2 * cores : 8 ))}
exec .venv/bin/python -m pytest -q -ra --durations=30 -n "$workers" --dist loadgroup "$@"
