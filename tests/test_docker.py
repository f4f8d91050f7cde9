"""The docker-compose cluster's structure (no container engine runs on our machines)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import yaml

from vastray.actors.node import build_parser as build_node_parser
from vastray.cli import build_parser

DOCKER = Path(__file__).resolve().parents[1] / "docker"


def compose() -> dict:
    return yaml.safe_load((DOCKER / "docker-compose.yml").read_text())


def test_coordinator_and_nodes_share_store_keys_and_port():
    services = compose()["services"]
    assert {"keys", "coordinator", "node"} <= set(services)
    coordinator, node = services["coordinator"]["command"], services["node"]["command"]
    listen = coordinator[coordinator.index("--listen") + 1]
    port = listen.rsplit(":", 1)[1]
    assert node[node.index("--coordinator") + 1] == f"tcp://coordinator:{port}"
    assert coordinator[coordinator.index("--keys") + 1] == node[node.index("--keys") + 1]
    store = coordinator[1]
    data_mount = next(v for v in services["node"]["volumes"] if v.endswith(":ro") and "/data" in v)
    assert store.startswith(data_mount.split(":")[1])
    assert node[node.index("--bind") + 1] == "0.0.0.0"


def test_compose_commands_parse_with_the_real_cli():
    services = compose()["services"]
    parser = build_parser()
    args = parser.parse_args([a.replace("${NODES:-4}", "4") for a in services["coordinator"]["command"]])
    assert args.nodes == 4 and args.listen == "0.0.0.0:5555"
    args = parser.parse_args(services["keys"]["command"])
    assert args.output == "/keys" and args.keep_existing  # a second `up` keeps the keys
    args = build_node_parser().parse_args(services["node"]["command"][1:])
    assert args.coordinator == "tcp://coordinator:5555" and args.keys == "/keys"


def test_dockerfile_installs_the_package_with_its_entry_point():
    text = (DOCKER / "Dockerfile").read_text()
    package_dirs = tomllib.loads((DOCKER.parent / "pyproject.toml").read_text())[
        "tool"]["setuptools"]["package-dir"]
    for folder in {d.split("/")[0] for d in package_dirs.values()}:
        assert f"COPY {folder} ./{folder}" in text
    assert "pip install" in text and 'ENTRYPOINT ["vastray"]' in text
