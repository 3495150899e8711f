#!/usr/bin/env bash
# The main job on a fresh machine: set up, start the server, replay a walkthrough with the
# headless client over a built-in scene, print per-frame and mean epsilon / PSNR / SSIM.
# Extra arguments go to `pvs demo` (see `pvs demo --help`).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
source scripts/env.sh
exec .venv/bin/pvs demo "$@"
