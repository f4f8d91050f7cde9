"""The compose cluster for real, on a Docker engine: docker/Dockerfile built, then
docker/docker-compose.yml brought up (keys, a coordinator, 4 nodes) with `spec-ooc` and `async`;
every container exits 0, the outputs belong to the owner of the data folder, each node's log
names its rank once the coordinator has assigned it, and the image equals the single-process
render's bit for bit. Skips with a reason where no engine (or no compose) is reachable
(``../shared/tools/docker-engine.sh`` sets one up on a machine without a container registry).
Each run is a compose project of its own, taken down with its volumes even when it fails.

Also here, without an engine: hand-started nodes (as compose starts them, no ``--rank``) log
``node ?:`` only until the coordinator gives them their rank."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
import yaml

from vastray.render.imageio import read_exr

from scenes import free_port, reap

REPO = Path(__file__).resolve().parents[1]
COMPOSE_FILE = REPO / "docker" / "docker-compose.yml"
IMAGE = "vastray:latest"  # the compose file's `image:`
NODES = 4
DATA_OWNER = 4321  # a host user that is neither root nor the image's uid 1000
RENDER = ["--width", "64", "--height", "48", "--spp", "2"]
TIMEOUT_S = 900  # a busy 2-core machine, 6 containers each compiling numba's kernels


def _works(command: list[str]) -> bool:
    try:
        return subprocess.run(command, capture_output=True, timeout=60).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def docker_client() -> str | None:
    """A docker client that reaches an engine: the one on PATH, or Debian's (matched to its
    engine, where another client comes first on PATH)."""
    for client in dict.fromkeys(filter(None, [shutil.which("docker"), "/usr/bin/docker"])):
        if os.access(client, os.X_OK) and _works([client, "info"]):
            return client
    return None


def compose_command(client: str) -> list[str] | None:
    """Compose v2 (``docker compose``) or v1.29 (``docker-compose``): the file works with both."""
    for command in ([client, "compose"], [shutil.which("docker-compose") or "docker-compose"]):
        if _works([*command, "version"]):
            return command
    return None


def run(command: list, timeout: float = 300, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([str(c) for c in command], capture_output=True, text=True,
                          timeout=timeout, **kwargs)


@pytest.fixture(scope="module")
def engine():
    """(docker client, compose command), the image built once for every scheduler."""
    # CI, where it has just set an engine up, asks for a failure rather than a skip
    missing = pytest.fail if os.environ.get("VASTRAY_REQUIRE_DOCKER") else pytest.skip
    client = docker_client()
    if client is None:
        missing("no Docker engine reachable (`docker info` fails); "
                "../shared/tools/docker-engine.sh sets one up")
    compose = compose_command(client)
    if compose is None:
        missing("a Docker engine but no compose (`docker compose` or `docker-compose`)")
    # host networking: the build's pip needs the package index (on machines with no registry
    # but PyPI's, the container network may reach nothing); the layers stay cached
    build = run([client, "build", "--network", "host", "-f", COMPOSE_FILE.parent / "Dockerfile",
                 "-t", IMAGE, REPO], timeout=TIMEOUT_S)
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    return client, compose


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A small store and its single-process render with the options the cluster is given."""
    folder = tmp_path_factory.mktemp("compose-scene")
    vastray = [sys.executable, "-m", "vastray.cli"]
    made = run([*vastray, "generate", "rm", "-o", folder / "store", "--resolution", "32",
                "--grid", "2x2x2"])
    assert made.returncode == 0, made.stderr
    reference = run([*vastray, "render", folder / "store", "-o", folder / "reference.exr",
                     *RENDER, "--quiet"], timeout=600)
    assert reference.returncode == 0, reference.stderr
    return folder


def project_containers(client: str, project: str) -> list[dict]:
    ids = run([client, "ps", "-aq", "--filter", f"label=com.docker.compose.project={project}"])
    if not ids.stdout.split():
        return []
    inspect = run([client, "inspect", *ids.stdout.split()])
    return json.loads(inspect.stdout)


def project_leftovers(client: str, project: str) -> list[str]:
    """What the project left behind: containers, volumes and networks (by compose's label)."""
    label = f"label=com.docker.compose.project={project}"
    return (run([client, "ps", "-aq", "--filter", label]).stdout.split()
            + run([client, "volume", "ls", "-q", "--filter", label]).stdout.split()
            + run([client, "network", "ls", "-q", "--filter", label]).stdout.split())


def override(data: Path, scheduler: str) -> dict:
    """The shipped file's services pointed at ``data`` (instead of docker/data), with the
    coordinator's own command plus a small image and a reference to compare against."""
    services = yaml.safe_load(COMPOSE_FILE.read_text())["services"]
    command = [str(NODES) if a == "${NODES:-4}" else a for a in services["coordinator"]["command"]]
    command[command.index("--scheduler") + 1] = scheduler
    command += [*RENDER, "--reference", "/data/reference.exr"]
    return {"services": {
        "keys": {"volumes": [f"{data}:/data:ro"]},
        "coordinator": {"command": command, "volumes": [f"{data}:/data"]},
        "node": {"volumes": [f"{data}:/data:ro"]},
    }}


@pytest.mark.timeout(2400)  # the image's build and the cluster's run may each take TIMEOUT_S
@pytest.mark.slow
@pytest.mark.parametrize("scheduler", ["spec-ooc", "async"])
def test_the_compose_cluster_renders_the_single_process_image(engine, scene, tmp_path, scheduler):
    client, compose = engine
    data = tmp_path / "data"
    data.mkdir()
    shutil.copytree(scene / "store", data / "store")
    shutil.copy(scene / "reference.exr", data / "reference.exr")
    owner = DATA_OWNER if os.geteuid() == 0 else os.getuid()
    if os.geteuid() == 0:  # the outputs must be this user's, not root's nor the image's
        for path in [data, *data.rglob("*")]:
            os.chown(path, owner, owner)
    (tmp_path / "override.yml").write_text(yaml.safe_dump(override(data, scheduler)))
    project = f"vastray-test-{uuid.uuid4().hex[:8]}"
    base = [*compose, "-p", project, "-f", COMPOSE_FILE, "-f", tmp_path / "override.yml"]
    env = {**os.environ, "NODES": str(NODES), "NODE_CPUS": "1"}
    start = time.monotonic()
    try:
        up = run([*base, "up", "-d", "--no-build", "--scale", f"node={NODES}"], env=env,
                 timeout=TIMEOUT_S)
        assert up.returncode == 0, up.stdout + up.stderr
        while True:  # every container done (the keys service exits first)
            containers = project_containers(client, project)
            if all(c["State"]["Status"] in ("exited", "dead") for c in containers):
                break
            assert time.monotonic() - start < TIMEOUT_S, "the cluster did not finish in time"
            time.sleep(2)
        logs = run([*base, "logs", "--no-color"], env=env).stdout
        by_service: dict[str, list[dict]] = {}
        for c in containers:
            by_service.setdefault(c["Config"]["Labels"]["com.docker.compose.service"], []).append(c)
        assert {s: len(cs) for s, cs in by_service.items()} == {
            "keys": 1, "coordinator": 1, "node": NODES}, logs
        codes = {c["Name"]: c["State"]["ExitCode"] for c in containers}
        assert set(codes.values()) == {0}, f"{codes}\n{logs}"
        ranks = set()
        for node in by_service["node"]:
            log = run([client, "logs", node["Id"]]).stderr.splitlines()
            joined = [i for i, line in enumerate(log) if re.search(r"joined \S+ as node", line)]
            assert joined, log
            rank = int(re.search(r"as node (\d+) of", log[joined[0]])[1])
            ranks.add(rank)
            assert all(line.startswith(f"node {rank}: ") for line in log[joined[0]:]), log
        assert ranks == set(range(NODES)), logs
        # the coordinator is not --quiet: its log's last line says where the image went
        said = run([client, "logs", by_service["coordinator"][0]["Id"]]).stderr
        assert "wrote /data/out/image.exr" in said, said
    finally:
        down = run([*base, "down", "-v", "--remove-orphans", "--timeout", "5"], env=env)
    assert down.returncode == 0, down.stderr
    assert project_leftovers(client, project) == []
    out = data / "out"
    for name in ("image.exr", "image.png", "report.json"):
        assert (out / name).stat().st_uid == owner and (out / name).stat().st_gid == owner, name
    report = json.loads((out / "report.json").read_text())
    assert report["scheduler"] == scheduler and report["counters"]["nodes"] == NODES, report
    assert report["error"]["mse"] == 0.0 and report["error"]["max_abs_diff"] == 0.0, report
    assert np.array_equal(read_exr(out / "image.exr"), read_exr(data / "reference.exr"))
    # each node's container holds it to NODE_CPUS: it reads its cgroup's throttled time
    held = [node["counters"].get("cpu_throttled_s") for node in report["counters"]["per_node"]]
    assert all(isinstance(s, float) and s >= 0.0 for s in held), held


# ----------------------------------------------------- node log prefixes, without an engine


def test_hand_started_nodes_log_their_rank_once_assigned(scene, tmp_path):
    vastray = [sys.executable, "-m", "vastray.cli"]
    assert run([*vastray, "keys", "-o", tmp_path / "keys", "--node", "node"]).returncode == 0
    port = free_port()
    logs = [tmp_path / f"n{i}.log" for i in range(2)]
    nodes = []
    for log in logs:  # as compose starts them: no --rank, one shared key folder
        with open(log, "wb") as err:
            nodes.append(subprocess.Popen(
                [*vastray, "node", "--coordinator", f"tcp://127.0.0.1:{port}", "--keys",
                 tmp_path / "keys", "--key-name", "node", "--timeout", "120"],
                stdout=subprocess.DEVNULL, stderr=err))
    try:
        coordinator = run([*vastray, "render", scene / "store", "-o", tmp_path / "image.exr",
                           "--nodes", "2", "--listen", f"127.0.0.1:{port}", "--keys",
                           tmp_path / "keys", "--width", "16", "--height", "12", "--spp", "1",
                           "--quiet"], timeout=600)
    finally:
        reap(nodes)
    texts = [log.read_text().splitlines() for log in logs]
    assert coordinator.returncode == 0, coordinator.stderr + "\n".join(map(str, texts))
    ranks = set()
    for lines in texts:
        joined = next(i for i, line in enumerate(lines) if " joined " in line)
        assert all(line.startswith("node ?: ") for line in lines[:joined]), lines
        rank = int(re.search(r"as node (\d) of 2", lines[joined])[1])
        assert all(line.startswith(f"node {rank}: ") for line in lines[joined:]), lines
        ranks.add(rank)
    assert ranks == {0, 1}
