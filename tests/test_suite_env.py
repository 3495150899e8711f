"""The test command's environment: processes the suite starts write bytecode (where a machine
sets PYTHONDONTWRITEBYTECODE and the venv holds none, each server, worker and CLI run compiled
numpy, scipy, numba and the project from source again; docs/getting-started.md)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FLAG = "import sys; print(sys.dont_write_bytecode)"


def test_a_process_a_test_starts_writes_bytecode():
    out = subprocess.run([sys.executable, "-c", FLAG], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "False"


def test_the_scripts_environment_writes_bytecode_where_the_machine_says_not_to():
    # The warm-up and the benchmarks run outside pytest, under scripts/env.sh.
    cmd = f'export PYTHONDONTWRITEBYTECODE=1; source scripts/env.sh; "{sys.executable}" -c "{FLAG}"'
    out = subprocess.run(["bash", "-c", cmd], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "False"
    # And the check itself can fail: with the variable left set, the flag is on.
    cmd = f'export PYTHONDONTWRITEBYTECODE=1; "{sys.executable}" -c "{FLAG}"'
    out = subprocess.run(["bash", "-c", cmd], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "True"
