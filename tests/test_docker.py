"""The docker-compose cluster, checked without a container engine (none runs on our machines):
the compose file against the Compose Specification's schema, the image's entrypoint run for
real as root and as uid 1000 against root-owned folders standing in for the volumes, and the
build context computed from .dockerignore by Docker's rules."""

from __future__ import annotations

import copy
import functools
import json
import os
import re
import shutil
import stat
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

import pytest
import yaml
from dockerignore import DockerIgnore, build_context, read_patterns

from vastray.actors.node import build_parser as build_node_parser
from vastray.cli import build_parser

from scenes import free_port

REPO = Path(__file__).resolve().parents[1]
DOCKER = REPO / "docker"
SCHEMA = Path(__file__).resolve().parent / "schemas" / "compose-spec.json"
ENTRYPOINT = DOCKER / "entrypoint.py"
IMAGE_UID = 1000  # the Dockerfile's `useradd --uid 1000 vastray`


def compose() -> dict:
    return yaml.safe_load((DOCKER / "docker-compose.yml").read_text())


_VARIABLE = re.compile(r"\$(?:(\$)|\{(\w+)(?:(:?-)([^}]*))?\}|(\w+))")


def interpolate(value, env: dict[str, str]):
    """Compose's variable interpolation (``$$``, ``$VAR``, ``${VAR}``, ``${VAR:-default}``,
    ``${VAR-default}``) over every string of a loaded compose file."""
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def sub(m: re.Match) -> str:
        dollar, name, op, default, bare = m.groups()
        if dollar:
            return "$"
        name = name or bare
        if op == ":-" and not env.get(name):
            return default
        if op == "-" and name not in env:
            return default
        return env.get(name, "")

    return _VARIABLE.sub(sub, value)


def services(env: dict[str, str] | None = None) -> dict:
    return interpolate(compose(), env or {})["services"]


# ---------------------------------------------------------------------------- the compose file

def schema_errors(document: dict) -> list[str]:
    jsonschema = pytest.importorskip("jsonschema", reason="the dev extra installs jsonschema")
    validator = jsonschema.Draft7Validator(json.loads(SCHEMA.read_text()))
    return [f"{'/'.join(map(str, e.absolute_path))}: {e.message}"
            for e in validator.iter_errors(document)]


@pytest.mark.parametrize("env", [{}, {"NODES": "8", "NODE_CPUS": "1.5"}])
def test_compose_file_validates_against_the_compose_spec_schema(env):
    document = interpolate(compose(), env)
    assert schema_errors(document) == []
    assert document["services"]["node"]["cpus"] == env.get("NODE_CPUS", "1")


def test_the_schema_check_catches_a_broken_compose_file():
    # the check above can fail: a misspelt wait condition and an unknown key are refused
    document = interpolate(compose(), {})
    broken = copy.deepcopy(document)
    broken["services"]["node"]["depends_on"]["keys"]["condition"] = "service_completed"
    broken["services"]["coordinator"]["volume"] = ["./data:/data"]
    errors = schema_errors(broken)
    assert any("node/depends_on" in e for e in errors), errors
    assert any("coordinator: 'volume' does not match" in e for e in errors), errors


def _compose_commands() -> list[list[str]]:
    """Every compose here: v2 (the docker CLI plugin, or a standalone ``docker-compose`` 2.x)
    and v1.29 (``docker-compose``, the one Debian and PyPI ship)."""
    found = []
    for command in (["docker", "compose"], ["docker-compose"]):
        if shutil.which(command[0]) is None:
            continue
        version = subprocess.run([*command, "version", "--short"], capture_output=True,
                                 text=True, timeout=60)
        if version.returncode == 0:
            found.append(command)
    return found


def test_the_file_needs_no_compose_v2_key_and_names_its_project_for_both():
    # v1.29 refuses a top-level `name:` (a v2 key); docker/.env names the project for both
    assert "name" not in compose()
    env = dict(line.split("=", 1) for line in (DOCKER / ".env").read_text().splitlines()
               if line and not line.startswith("#"))
    assert env == {"COMPOSE_PROJECT_NAME": "vastray"}


def test_a_compose_implementation_accepts_the_file():
    commands = _compose_commands()
    if not commands:
        pytest.skip("no compose here (`docker compose` or `docker-compose`); the schema test "
                    "above checks the file")
    for command in commands:
        run = subprocess.run([*command, "-f", str(DOCKER / "docker-compose.yml"), "config"],
                             capture_output=True, text=True, timeout=60,
                             env={**os.environ, "NODES": "2", "NODE_CPUS": "2"})
        assert run.returncode == 0, (command, run.stderr)
        config = yaml.safe_load(run.stdout)
        assert float(config["services"]["node"]["cpus"]) == 2.0
        assert "2" in config["services"]["coordinator"]["command"]


def test_coordinator_and_nodes_share_store_keys_and_port():
    svc = services()
    assert {"keys", "coordinator", "node"} <= set(svc)
    coordinator, node = svc["coordinator"]["command"], svc["node"]["command"]
    listen = coordinator[coordinator.index("--listen") + 1]
    port = listen.rsplit(":", 1)[1]
    assert node[node.index("--coordinator") + 1] == f"tcp://coordinator:{port}"
    assert coordinator[coordinator.index("--keys") + 1] == node[node.index("--keys") + 1]
    # its log (`docker-compose logs coordinator`) says where the image went and whether a
    # frame was rendered again after a node loss: never --quiet (issue 42)
    assert "--quiet" not in coordinator
    store = coordinator[1]
    data_mount = next(v for v in svc["node"]["volumes"] if v.endswith(":ro") and "/data" in v)
    assert store.startswith(data_mount.split(":")[1])
    assert node[node.index("--bind") + 1] == "0.0.0.0"


def test_compose_commands_parse_with_the_real_cli():
    svc = services({"NODES": "4"})
    parser = build_parser()
    args = parser.parse_args(svc["coordinator"]["command"])
    assert args.nodes == 4 and args.listen == "0.0.0.0:5555"
    args = parser.parse_args(svc["keys"]["command"])
    assert args.output == "/keys" and args.keep_existing  # a second `up` keeps the keys
    node_key = args.node
    args = build_node_parser().parse_args(svc["node"]["command"][1:])
    assert args.coordinator == "tcp://coordinator:5555" and args.keys == "/keys"
    assert [args.key_name] == node_key  # the nodes' key is made, and on the allow-list


def test_every_service_runs_as_the_owner_of_the_data_folder_and_owns_what_it_writes():
    svc = services()
    for name, service in svc.items():
        # the entrypoint takes its user from /data: the same one in every container, so the
        # nodes and the coordinator can read the keys (0600) the keys service wrote
        assert any(v.split(":")[:2] == ["./data", "/data"] for v in service["volumes"]), name
        assert "user" not in service, f"{name}: the image starts as root to hand over volumes"
    assert svc["keys"]["environment"]["VASTRAY_WRITABLE"] == "/keys"
    assert "keys:/keys" in svc["keys"]["volumes"]  # read-write only where the keys are made
    args = build_parser().parse_args(svc["coordinator"]["command"])
    writable = svc["coordinator"]["environment"]["VASTRAY_WRITABLE"].split(":")
    for output in (args.output, args.png, args.report):
        assert str(Path(output).parent) in writable, output
    assert "VASTRAY_WRITABLE" not in svc["node"].get("environment", {})  # nodes write nothing


def test_each_node_is_limited_to_its_share_of_the_cpus_and_takes_its_threads_from_it():
    # the limit is the cgroup quota that vastray.scene.cpus turns into the node's default
    # thread count (tests/test_cpus.py): a --threads on the coordinator would override it
    # with one count for every node, whatever its limit
    assert services()["node"]["cpus"] == "1"
    assert services({"NODE_CPUS": "3"})["node"]["cpus"] == "3"
    assert "--threads" not in services()["coordinator"]["command"]


# ------------------------------------------------------------------------------ the Dockerfile

def dockerfile() -> str:
    return (DOCKER / "Dockerfile").read_text()


def copy_sources() -> list[tuple[str, str]]:
    """(source, destination) of every COPY line (several sources: one pair each)."""
    pairs = []
    for line in dockerfile().splitlines():
        if line.startswith("COPY "):
            *sources, dest = [w for w in line.split()[1:] if not w.startswith("--")]
            pairs += [(s, dest) for s in sources]
    return pairs


def package_folders() -> set[str]:
    dirs = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    return {d.split("/")[0] for d in dirs.values()}


def test_dockerfile_copies_every_package_the_license_and_the_entrypoint():
    sources = {s for s, _ in copy_sources()}
    assert package_folders() | {"pyproject.toml", "README.md", "LICENSE"} <= sources
    assert ("docker/entrypoint.py", "/usr/local/bin/vastray-entrypoint") in copy_sources()
    text = dockerfile()
    assert "pip install" in text
    assert 'ENTRYPOINT ["python", "/usr/local/bin/vastray-entrypoint"]' in text
    assert f"useradd --create-home --uid {IMAGE_UID} --gid {IMAGE_UID} vastray" in text
    assert "\nUSER " not in text  # starts as root to hand the volumes over, then drops root


# ------------------------------------------------------------------------- the build context

def test_the_dockerignore_port_agrees_with_moby_patternmatcher():
    # cases from moby/patternmatcher's TestMatches (MatchesOrParentMatches)
    cases = [("**", "dir/file", True), ("dir/**", "dir/dir2/file", True),
             ("**/dir", "dir/file", True), ("**/dir2/*", "dir/dir2/file", True),
             ("**/file*.txt", "dir/dir/file.txt", True), ("**/**/*.txt2", "dir/dir/file.txt", False),
             ("**/*.txt", "file.txt", True), ("a/*.txt", "a/dir/file.txt", False),
             ("a[b-d]e", "aae", False), ("a[^b-d]e", "aze", True), (".*", "foo", False),
             ("abc.def", "abcZdef", False), ("abc?def", "abcZdef", True),
             ("abc/**", "abc", False), ("**/.foo", "bar.foo", False),
             ("dist/*.whl", "dist/proxy.py-2.4.0rc3.dev36+g08acad9-py3-none-any.whl", True),
             ("*.store", "sub/x.store", False)]  # anchored at the root, unlike .gitignore
    for pattern, path, excluded in cases:
        assert DockerIgnore([pattern]).excluded(path) == excluded, (pattern, path)
    assert not DockerIgnore(["**", "!util/docker/web"]).excluded("util/docker/web/foo")
    assert DockerIgnore(["**", "!util/docker/web", "util/docker/web/foo"]).excluded(
        "util/docker/web/foo")
    assert read_patterns("\ufeff# c\n /a/b/ \n!  ./c\n\n") == ["a/b", "!c"]


def test_the_build_context_holds_the_sources_and_no_data_store_vcs_or_venv(tmp_path):
    context = tmp_path / "repo"
    wanted = ["pyproject.toml", "README.md", "LICENSE", "docker/entrypoint.py",
              "src/vastray/cli.py", "scene/store.py", "render/tracer.py",
              "schedule/spec_ooc.py", "transport/codec.py", "actors/node.py"]
    unwanted = [".git/HEAD", ".git/objects/ab/cdef", "docker/data/store/manifest.json",
                "docker/data/store/domain_000.npz", "docker/data/out/image.exr",
                "rm.store/manifest.json", "scene/bunny.store/manifest.json", "samples/bunny.ply",
                "rm.exr", "volume.npy", "out/a.png", ".venv/bin/python", "venv/lib/x.py",
                ".pytest_cache/v/x", "src/vastray/__pycache__/cli.cpython-311.pyc",
                "src/vastray.egg-info/PKG-INFO", "tests/test_docker.py", "docs/DESIGN.md",
                "bench/out.json", "docker/docker-compose.yml"]
    for name in wanted + unwanted:
        (context / name).parent.mkdir(parents=True, exist_ok=True)
        (context / name).write_text("x")
    shutil.copy(REPO / ".dockerignore", context / ".dockerignore")
    assert build_context(context) == set(wanted)


def test_the_repository_context_has_everything_the_dockerfile_copies():
    files = build_context(REPO)
    assert not any(f.startswith((".git/", "docker/data/")) or ".store/" in f for f in files)
    for source, _ in copy_sources():
        if (REPO / source).is_dir():
            tracked = subprocess.run(["git", "ls-files", source], cwd=REPO, capture_output=True,
                                     text=True).stdout.split()
            assert tracked and set(tracked) <= files, source
        else:
            assert source in files, source
    for folder in package_folders():
        assert any(f.startswith(f"{folder}/") and f.endswith("__init__.py") for f in files)


# --------------------------------------------------------------------------- the entrypoint

needs_root = pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("setpriv") is None,
    reason="runs the entrypoint as root and as uid 1000 (setpriv): needs root and util-linux")


@pytest.fixture
def volumes(monkeypatch):
    """Root-owned folders as a fresh container sees them: ``data`` (the bind-mounted
    docker/data, root-owned as Docker creates it when missing) and ``keys`` (a fresh named
    volume). Outside pytest's private tmp folder, so uid 1000 can reach them. The commands
    run keep numba's cache there too, not in the home of whoever is uid 1000 here."""
    root = Path(tempfile.mkdtemp(prefix="vastray-docker-"))
    root.chmod(0o755)
    for name in ("data", "keys", "numba-cache"):
        (root / name).mkdir(mode=0o755)
    (root / "numba-cache").chmod(0o1777)  # for the one uid (not root) a test runs commands as
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(root / "numba-cache"))  # for the subprocesses
    try:
        problem = _uid_1000_cannot_import_vastray()
        if problem:
            pytest.skip(f"uid {IMAGE_UID} cannot import vastray with {sys.executable} here "
                        f"(an install it cannot read?): {problem}")
        yield root
    finally:
        shutil.rmtree(root)


@functools.cache
def _uid_1000_cannot_import_vastray() -> str:
    """Why uid 1000 cannot run this environment's vastray ('' when it can)."""
    probe = subprocess.run(["setpriv", f"--reuid={IMAGE_UID}", f"--regid={IMAGE_UID}",
                            "--clear-groups", sys.executable, "-c", "import vastray.cli"],
                           capture_output=True, text=True, cwd="/", timeout=120,
                           env={**os.environ, "NUMBA_DISABLE_JIT": "1"})  # no cache written
    return "" if probe.returncode == 0 else (probe.stderr.strip().splitlines() or ["?"])[-1]


def entrypoint(args, env: dict, as_uid: int | None = None, cwd=None, **kwargs):
    """Run docker/entrypoint.py ARGS as the image runs it (as root, or with ``as_uid`` as
    ``docker run --user`` would); ``vastray`` is this environment's."""
    prefix = [] if as_uid is None else ["setpriv", f"--reuid={as_uid}", f"--regid={as_uid}",
                                        "--clear-groups"]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}", **env}
    return subprocess.run([*prefix, sys.executable, str(ENTRYPOINT), *map(str, args)], env=env,
                          cwd=cwd or "/", capture_output=True, text=True, timeout=120, **kwargs)


def owner(path: Path) -> tuple[int, int]:
    st = path.stat()
    return st.st_uid, st.st_gid


@needs_root
def test_without_the_entrypoint_uid_1000_cannot_write_the_root_owned_volume(volumes):
    # the issue, reproduced: this is what the keys service did before (USER vastray)
    home = volumes / "home"  # /home/vastray in the image
    home.mkdir()
    os.chown(home, IMAGE_UID, IMAGE_UID)
    run = subprocess.run(["setpriv", f"--reuid={IMAGE_UID}", f"--regid={IMAGE_UID}",
                          "--clear-groups", Path(sys.executable).parent / "vastray", "keys", "-o",
                          volumes / "keys"], capture_output=True, text=True, cwd="/",
                         env={**os.environ, "HOME": str(home)})
    assert run.returncode != 0 and "Permission" in run.stderr
    assert not (volumes / "keys" / "coordinator.key").exists()


@needs_root
def test_keys_service_writes_its_keys_into_the_root_owned_volume_as_uid_1000(volumes):
    keys, data = volumes / "keys", volumes / "data"
    env = {"VASTRAY_WRITABLE": str(keys), "VASTRAY_OWNER_FROM": str(data)}
    run = entrypoint(["keys", "-o", keys, "--keep-existing"], env)
    assert run.returncode == 0, run.stderr
    key = keys / "coordinator.key"
    assert owner(key) == owner(keys) == (IMAGE_UID, IMAGE_UID)  # data is root's: the image user
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    first = key.read_text()
    again = entrypoint(["keys", "-o", keys, "--keep-existing"], env)  # a second `up`
    assert again.returncode == 0, again.stderr
    assert key.read_text() == first


@needs_root
def test_coordinator_creates_and_writes_the_output_folder_as_the_data_owner(volumes):
    data, host_user = volumes / "data", 4321  # a host user that is not uid 1000
    os.chown(data, host_user, host_user)
    out = data / "out"  # absent: Docker would create it root-owned, the entrypoint makes it
    env = {"VASTRAY_WRITABLE": str(out), "VASTRAY_OWNER_FROM": str(data)}
    run = entrypoint(["generate", "rm", "-o", out / "tiny.store", "--resolution", "8",
                      "--grid", "1x1x1"], env)
    assert run.returncode == 0, run.stderr
    written = list((out / "tiny.store").iterdir())
    assert written and all(owner(p) == (host_user, host_user) for p in [out, *written])


@needs_root
def test_a_folder_docker_created_as_root_is_handed_over_with_what_is_in_it(volumes):
    out, data = volumes / "data" / "out", volumes / "data"
    (out / "old").mkdir(parents=True)
    (out / "old" / "report.json").write_text("{}")
    env = {"VASTRAY_WRITABLE": str(out), "VASTRAY_OWNER_FROM": str(data)}
    run = entrypoint(["keys", "-o", out / "old", "--keep-existing"], env)
    assert run.returncode == 0, run.stderr
    assert all(owner(p) == (IMAGE_UID, IMAGE_UID)
               for p in [out, out / "old", out / "old" / "report.json", out / "old" / "coordinator.key"])
    assert (out / "old" / "report.json").read_text() == "{}"  # handed over, not replaced


@needs_root
def test_an_output_folder_that_cannot_be_made_is_refused_in_one_line(volumes):
    data = volumes / "data"
    (data / "out").write_text("a file where the output folder should be")
    run = entrypoint(["keys", "-o", data / "out" / "k"],
                     {"VASTRAY_WRITABLE": str(data / "out"), "VASTRAY_OWNER_FROM": str(data)})
    assert run.returncode == 1 and "Traceback" not in run.stderr
    assert run.stderr.startswith(f"vastray-entrypoint: error: {data / 'out'}: cannot hand it to "
                                 f"uid {IMAGE_UID}: File exists") and run.stderr.count("\n") == 1
    assert (data / "out").read_text().startswith("a file")  # left as it was


@needs_root
def test_started_as_uid_1000_it_refuses_a_root_owned_volume_in_one_line(volumes):
    keys = volumes / "keys"
    run = entrypoint(["keys", "-o", keys], {"VASTRAY_WRITABLE": str(keys)}, as_uid=IMAGE_UID)
    assert run.returncode == 1
    assert run.stderr.strip() == run.stderr.strip().splitlines()[0], run.stderr  # one line
    assert f"{keys}: not writable by uid {IMAGE_UID} (owned by uid 0)" in run.stderr
    assert "Traceback" not in run.stderr and not any(keys.iterdir())


def _uid_1000_can_run_python() -> bool:
    # setpriv itself may start this interpreter where uid 1000 could not (it execs with root's
    # capabilities): here it lives under /root, 0700, so a uid-1000 process cannot exec it
    probe = subprocess.run(["setpriv", f"--reuid={IMAGE_UID}", f"--regid={IMAGE_UID}",
                            "--clear-groups", "/bin/sh", "-c", 'exec "$0" -c pass',
                            sys.executable], capture_output=True, cwd="/")
    return probe.returncode == 0


@needs_root
def test_started_as_uid_1000_it_runs_vastray_where_it_may_write(volumes):
    if not _uid_1000_can_run_python():
        pytest.skip(f"uid {IMAGE_UID} cannot execute {sys.executable} on this machine")
    keys = volumes / "keys"
    os.chown(keys, IMAGE_UID, IMAGE_UID)  # a volume made from the image's /keys
    run = entrypoint(["keys", "-o", keys], {"VASTRAY_WRITABLE": str(keys)}, as_uid=IMAGE_UID)
    assert run.returncode == 0, run.stderr
    assert owner(keys / "coordinator.key") == (IMAGE_UID, IMAGE_UID)


@needs_root
@pytest.mark.slow
def test_the_compose_cluster_renders_through_the_entrypoint_on_root_owned_volumes(volumes):
    """The three services as compose starts them, with their environment and the commands
    pointed at the temp folders (and loopback instead of the compose network): keys, then a
    coordinator and one node, every one started as root and run as uid 1000."""
    keys, data = volumes / "keys", volumes / "data"
    store = data / "store"
    made = subprocess.run([Path(sys.executable).parent / "vastray", "generate", "rm", "-o", store,
                           "--resolution", "16", "--grid", "2x1x1"], capture_output=True, text=True,
                          env={k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"})
    assert made.returncode == 0, made.stderr  # root-owned, as a root host user leaves it
    svc, port = services({"NODES": "1"}), free_port()

    def command(name: str) -> list[str]:
        args = [a.replace("/data", str(data)).replace("/keys", str(keys))
                .replace("0.0.0.0:5555", f"127.0.0.1:{port}").replace("coordinator:5555",
                                                                      f"127.0.0.1:{port}")
                for a in svc[name]["command"]]
        args = ["127.0.0.1" if a == "0.0.0.0" else a for a in args]  # loopback only here
        return args + (["--width", "32", "--height", "24", "--spp", "1"]
                       if name == "coordinator" else [])

    def env(name: str) -> dict:
        return {"VASTRAY_OWNER_FROM": str(data),
                **{k: v.replace("/data", str(data)).replace("/keys", str(keys))
                   for k, v in svc[name].get("environment", {}).items()}}

    made = entrypoint(command("keys"), env("keys"))
    assert made.returncode == 0, made.stderr
    node = subprocess.Popen(
        [sys.executable, str(ENTRYPOINT), *command("node")], cwd="/", stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}",
             **env("node")})
    try:
        run = entrypoint(command("coordinator"), env("coordinator"))
    finally:
        try:
            _, node_err = node.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            node.kill()
            _, node_err = node.communicate()
    assert run.returncode == 0, run.stderr + node_err
    out = data / "out"
    for name in ("image.exr", "image.png", "report.json"):
        assert owner(out / name) == (IMAGE_UID, IMAGE_UID), name
    report = json.loads((out / "report.json").read_text())
    assert report["counters"]["nodes"] == 1
