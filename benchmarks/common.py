"""Helpers the benchmarks share: a free loopback port, a process's RSS and CPU time, stopping a
process, the machine line, the command line, markdown tables and Prometheus counters.

Imports nothing of the project, so any benchmark (and its test) can use it.
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import socket
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now (the OS picks it; another process may take it later)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def rss_bytes(pid: int) -> int:
    """Resident set size of process ``pid``, bytes (``/proc/PID/status``; 0 when unreadable)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (``/proc/PID/stat``; NaN when
    unreadable)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def stop_process(proc: subprocess.Popen, kill: bool = False, timeout: float = 20.0) -> None:
    """Stop ``proc``: SIGTERM (SIGKILL when ``kill``, a crash), then SIGKILL if it has not
    exited within ``timeout`` seconds; closes its stderr pipe."""
    if proc.poll() is None:
        proc.kill() if kill else proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
    if proc.stderr is not None:
        proc.stderr.close()


def machine() -> str:
    """CPU model, logical cores, memory and OS of this machine, one line."""
    model = platform.processor() or "unknown CPU"
    mem_s = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
        mem = next(int(x.split()[1]) for x in Path("/proc/meminfo").read_text().splitlines()
                   if x.startswith("MemTotal:"))
        mem_s = f", {mem / 2**20:.1f} GiB RAM"
    except (OSError, StopIteration, ValueError, IndexError):
        pass
    return f"{model}, {os.cpu_count()} logical cores{mem_s}, {platform.platform()}"


def command_line(module: str, argv: Sequence[str] | None = None) -> str:
    """How the run was started, as a shell line one can paste: ``python -m MODULE ARGS``
    (``argv`` default ``sys.argv[1:]``; arguments quoted where the shell needs it)."""
    args = list(sys.argv[1:] if argv is None else argv)
    return shlex.join(["python", "-m", module, *args])


def header_lines(command: str, where: str) -> list[str]:
    """The command and machine lines a markdown report starts with (after its title)."""
    return [f"command: `{command}`", "", f"machine: {where}", ""]


def write_report(out: Path, stem: str, module: str, argv: Sequence[str], results: Any,
                 markdown: str) -> None:
    """Write a benchmark's ``out/stem.json`` (its command, machine line and ``results``) and
    ``out/stem.md`` (``markdown``), and say where."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(
        {"command": command_line(module, argv), "machine": machine(), "results": results},
        indent=1))
    (out / f"{stem}.md").write_text(markdown)
    print(f"wrote {out / stem}.md", flush=True)


def md_table(head: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[str]:
    """A markdown table, one string per line: ``head`` then ``rows`` (cells ``str()``-ed; a
    ``|`` inside a cell is escaped). ValueError when a row's length differs from the head's."""
    def cell(x: Any) -> str:
        return str(x).replace("|", "\\|")

    out = ["| " + " | ".join(cell(h) for h in head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        if len(r) != len(head):
            raise ValueError(f"a row of {len(r)} cells under a head of {len(head)}")
        out.append("| " + " | ".join(cell(x) for x in r) + " |")
    return out


def aimed_total(total: int, rays: int, converged: bool) -> str:
    """A table cell for a reference grown by aimed rays (``visibility.ray_aimed``): the
    triangles seen, the rays per triangle in brackets, * when the last doubling still added
    more than the convergence share."""
    return f"{total:,} ({rays}){'' if converged else ' *'}"


def prometheus_value(text: str, name: str) -> float:
    """The value of sample ``name`` (with its labels, exactly as exposed) in Prometheus text
    ``text``; NaN when absent."""
    for line in text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[-1])
    return float("nan")
