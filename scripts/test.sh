#!/usr/bin/env bash
# The test suite on a fresh machine: set up, lint, then pytest (real server on loopback, real
# WebSocket clients, headless pyrender). Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
source scripts/env.sh
.venv/bin/ruff check .
exec .venv/bin/python -m pytest -q -ra --durations=30 "$@"
