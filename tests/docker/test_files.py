"""The deployment files (docker/): Docker cannot run on these machines, so what can be checked
here is checked: the compose file parses, every service is built from our Dockerfile's own
targets (no image pulled from elsewhere), references between services hold, the proxy sends to
the server replicas' port, the settings the services pass are real settings, and the Dockerfile
copies files that exist and runs the README's set-up script."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from server.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
DOCKER = ROOT / "docker"


def _compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yml").read_text())


def _targets() -> set[str]:
    text = (DOCKER / "Dockerfile").read_text()
    return set(re.findall(r"^FROM\s+\S+\s+AS\s+(\S+)", text, flags=re.M | re.I))


def test_every_service_is_built_from_a_target_of_our_dockerfile():
    services = _compose()["services"]
    assert {"redis", "scheduler", "worker", "server1", "server2", "proxy"} <= set(services)
    targets = _targets()
    for name, svc in services.items():
        build = svc.get("build")
        assert build, f"{name} names an image nobody builds here"
        assert build["dockerfile"] == "docker/Dockerfile", name
        assert build["target"] in targets, (name, build["target"], targets)
        assert (DOCKER / build["context"]).resolve() == ROOT, name
        for dep in svc.get("depends_on", []):
            assert dep in services, (name, dep)


def test_the_proxy_sends_to_the_server_replicas_port():
    services = _compose()["services"]
    conf = (DOCKER / "nginx.conf").read_text()
    upstream = re.findall(r"^\s*server\s+([\w-]+):(\d+)", conf, flags=re.M)
    assert upstream, "no upstream servers in nginx.conf"
    for host, port in upstream:
        assert host in services, host
        cmd = services[host]["command"]
        assert cmd[cmd.index("--port") + 1] == port
    # WebSocket upgrade passes through (sessions stream over /ws).
    assert "proxy_set_header Upgrade $http_upgrade" in conf
    proxy_port = services["proxy"]["ports"][0].split(":")[-1]
    assert f"listen {proxy_port};" in conf


def test_the_services_pass_only_real_settings():
    env_names = {f"PVS_{name.upper()}" for name in Settings.model_fields}
    text = (DOCKER / "compose.yml").read_text()
    used = set(re.findall(r"\b(PVS_[A-Z_]+)\s*:", text))
    assert used, "compose passes no settings"
    unknown = used - env_names
    assert not unknown, f"not settings of server.settings.Settings: {sorted(unknown)}"


@pytest.mark.parametrize("line", [ln for ln in (DOCKER / "Dockerfile").read_text().splitlines()
                                  if ln.startswith("COPY") and "--from=" not in ln])
def test_the_dockerfile_copies_what_exists(line):
    parts = line.split()[1:-1]
    for src in parts:
        if src.startswith("--"):
            continue
        if src.endswith("*"):  # optional files (globs that may match nothing)
            continue
        assert (ROOT / src).exists(), src


def test_the_image_runs_the_readme_set_up_and_the_pvs_command():
    text = (DOCKER / "Dockerfile").read_text()
    # A stage copied from is a stage of this file.
    for stage in re.findall(r"COPY --from=(\S+)", text):
        assert stage in _targets(), stage
    assert "bash scripts/setup.sh" in text
    assert 'ENTRYPOINT ["pvs"]' in text
    assert 'pvs = "pvs_cli:main"' in (ROOT / "pyproject.toml").read_text()
