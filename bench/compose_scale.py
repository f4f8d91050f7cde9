"""The 8-container docker compose cluster with every distributed scheduler, beside the
simulator's prediction for the same runs (issue 38, part 4; the 16 local processes are
``bench/real_scale.py``).

docker/Dockerfile is built once; then, for each scheduler, docker/docker-compose.yml is
brought up as its own compose project (keys, a coordinator, ``--scale node=8``, each node
limited to ``NODE_CPUS`` = 0.25 CPU, so the 8 nodes share the machine's 2 cores), the
coordinator's command replaced by an override file (the shipped file stays as users use it:
its render line with this scheduler and the job below), and taken down with
``down -v`` whatever happens. Per scheduler: the cluster's wall time (``up`` to every
container exited), the coordinator's render time and ``busy_max`` (report.json), the
most throttled node's CPU-quota throttled time over its busy spans (its cgroup's
``cpu.stat``, summed over the cores it was held on: ``cpu_throttled_s``), the
simulated ``busy_max`` (this machine's calibrated constants, the virtual nodes sharing the
2 cores as the containers do, as ``real_scale.py`` simulates its processes) and, beside it,
the same simulation with each node held to its 0.25 CPU quota (a quarter-speed core of its
own, which an idle neighbour's share does not speed up), ray batches sent and domain loads
per node (real and simulated), coordinator messages per node, lost nodes, and whether the
image equals the single-process reference bit for bit (every scheduler here is lossless).

The job is ``real_scale.py``'s: rm at 64^3 in 4x4x2 = 32 domains (four a node), 320x240 px x
4 spp, one bounce, one thread a node, the nodes' default tile (the sort-first schedules
deal each pass's image-plane blocks to every node; until session 42 this bench gave them a
tile a node in a 1-spp pass); plus the compose file's own ``--cache 25%`` (8 domains a node; not for
``spec-insitu``, which refuses it: its nodes keep the domains they own loaded), and the
passes ``vastray render`` chose (its report's ``passes``), which the simulation follows. The
coordinator is given no ``--reference``: with one, each pass's error is wanted as it ends,
so the nodes render the passes apart, and out of core each pass then sweeps the domains
anew (session 56: 183 loads a node against 74 in one pass for ``image`` on these 8 nodes);
the shipped command has none, and the image is compared with the reference here.

Needs a Docker engine and compose; where none is reachable it says how to get one and
exits 2 (``bash ../shared/tools/docker-engine.sh`` on a machine without a registry).

    python bench/compose_scale.py                      # every scheduler (~6 min)
    python bench/compose_scale.py --quick --schedulers domain,async   # 160x120
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
import uuid
from dataclasses import asdict
from pathlib import Path

import numpy as np
import yaml
from bench_scenes import cached_rm
from real_scale import FULL, QUICK, machine_costs  # the same job and constants

from vastray.actors.job_options import JobOptions
from vastray.render.driver import shading_inputs
from vastray.render.imageio import read_exr
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.sim.cache import Domains
from vastray.sim.costs import CostModel
from vastray.sim.simulate import simulate

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the compose test's engine helpers
from test_compose_cluster import (  # noqa: E402
    COMPOSE_FILE,
    IMAGE,
    compose_command,
    docker_client,
    project_containers,
    project_leftovers,
    run,
)

SCHEDULERS = ["image", "spec-ooc", "domain", "async", "dynamic", "spec-insitu", "temporal"]
CACHE_PERCENT = 25  # the compose file's --cache 25%
#: in situ, a node keeps every domain it owns loaded: ``--cache`` is refused
NO_CACHE = ("spec-insitu",)
TIMEOUT_S = 900  # one scheduler's cluster, up to every container exited


def render_args(settings: RenderSettings) -> list[str]:
    return ["--width", str(settings.width), "--height", str(settings.height), "--spp",
            str(settings.spp), "--integrator", settings.integrator, "--bounces",
            str(settings.bounces), "--shadow-samples", str(settings.shadow_samples),
            "--seed", str(settings.seed)]


def job(scheduler: str, nodes: int, settings: RenderSettings, domains: int) -> JobOptions:
    """The job as the simulator sees it: the coordinator's command below, as options."""
    cache = None if scheduler in NO_CACHE else max(1, math.floor(domains * CACHE_PERCENT / 100))
    return JobOptions(scheduler=scheduler, threads=1, cache=cache)


def quota_costs(costs: CostModel, cpus: float) -> CostModel:
    """The same costs for nodes that each get ``cpus`` of a core and never more (a container's
    CPU quota, which an idle neighbour's share does not raise): every cost divided by ``cpus``,
    a core each (the wire's costs too: encoding, decoding and the bridge are CPU here)."""
    scaled = {f: v / cpus for f, v in asdict(costs).items()
              if f not in ("cores", "throughput", "machine")}
    return CostModel(**{**asdict(costs), **scaled, "cores": None})


def coordinator_command(scheduler: str, nodes: int, settings: RenderSettings) -> list[str]:
    """The shipped coordinator command with this scheduler and the job's options."""
    command = yaml.safe_load(COMPOSE_FILE.read_text())["services"]["coordinator"]["command"]
    command = [str(nodes) if a == "${NODES:-4}" else a for a in command]
    command[command.index("--scheduler") + 1] = scheduler
    at = command.index("--cache")
    assert command[at + 1] == f"{CACHE_PERCENT}%", command
    if scheduler in NO_CACHE:
        del command[at:at + 2]
    extra = ["--threads", "1", *render_args(settings)]
    return command + extra


def run_cluster(client: str, compose: list[str], data: Path, folder: Path, scheduler: str,
                nodes: int, node_cpus: str, settings: RenderSettings) -> tuple[float, dict, list]:
    """One compose project: up, wait for every container, logs, ``down -v``. Returns the
    wall seconds, the coordinator's report and the containers' exit codes by service."""
    out = data / "out"
    shutil.rmtree(out, ignore_errors=True)
    override = {"services": {
        "keys": {"volumes": [f"{data}:/data:ro"]},
        "coordinator": {"command": coordinator_command(scheduler, nodes, settings),
                        "volumes": [f"{data}:/data"]},
        "node": {"volumes": [f"{data}:/data:ro"]},
    }}
    (folder / f"override-{scheduler}.yml").write_text(yaml.safe_dump(override))
    project = f"vastray-scale-{uuid.uuid4().hex[:8]}"
    base = [*compose, "-p", project, "-f", COMPOSE_FILE, "-f", folder / f"override-{scheduler}.yml"]
    env = {**os.environ, "NODES": str(nodes), "NODE_CPUS": node_cpus}
    start = time.monotonic()
    try:
        up = run([*base, "up", "-d", "--no-build", "--scale", f"node={nodes}"], env=env,
                 timeout=TIMEOUT_S)
        if up.returncode != 0:
            raise RuntimeError(f"compose up failed:\n{up.stdout[-2000:]}{up.stderr[-2000:]}")
        while True:  # every container done (the keys service exits first)
            containers = project_containers(client, project)
            if containers and all(c["State"]["Status"] in ("exited", "dead") for c in containers):
                break
            if time.monotonic() - start > TIMEOUT_S:
                raise RuntimeError(f"{scheduler}: the cluster did not finish in {TIMEOUT_S} s")
            time.sleep(1)
        wall = time.monotonic() - start
        codes = sorted((c["Config"]["Labels"]["com.docker.compose.service"],
                        c["State"]["ExitCode"]) for c in containers)
        if any(code for _, code in codes):
            logs = run([*base, "logs", "--no-color", "--tail", "30"], env=env).stdout
            (folder / f"logs-{scheduler}.txt").write_text(logs)
            print(f"  {scheduler}: exit codes {codes}\n{logs[-3000:]}", flush=True)
    finally:
        down = run([*base, "down", "-v", "--remove-orphans", "--timeout", "5"], env=env)
        left = project_leftovers(client, project)
        if down.returncode != 0 or left:
            print(f"  {scheduler}: compose down failed or left {left}: {down.stderr[-1000:]}",
                  flush=True)
    report = json.loads((out / "report.json").read_text()) if (out / "report.json").is_file() \
        else {}
    return wall, report, codes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--nodes", type=int, default=8, help="node containers (default 8)")
    parser.add_argument("--node-cpus", default="0.25",
                        help="each node container's CPUs (default 0.25: 8 share 2 cores)")
    parser.add_argument("--quick", action="store_true", help="160x120 px instead of 320x240")
    parser.add_argument("--costs", metavar="FILE",
                        help="a calibration file (default: calibrate now, as real_scale.py does)")
    parser.add_argument("--keep", metavar="DIR", type=Path,
                        help="copy each run's report.json and overrides into DIR")
    parser.add_argument("--schedulers", default=",".join(SCHEDULERS),
                        help="comma-separated (default: every distributed one)")
    args = parser.parse_args()
    client = docker_client()
    compose = compose_command(client) if client else None
    if client is None or compose is None:
        print("no Docker engine with compose reachable: start one with "
              "`bash ../shared/tools/docker-engine.sh` (from the repository root)")
        sys.exit(2)
    start = time.perf_counter()
    print(f"+ docker build -t {IMAGE}", flush=True)
    build = run([client, "build", "--network", "host", "-f", COMPOSE_FILE.parent / "Dockerfile",
                 "-t", IMAGE, REPO], timeout=TIMEOUT_S)
    if build.returncode != 0:
        print(build.stdout[-3000:] + build.stderr[-3000:])
        sys.exit(1)
    settings = QUICK if args.quick else FULL
    store = cached_rm(64, (4, 4, 2))
    costs = machine_costs(store, args.costs, "costs-compose-scale.json")
    shared = costs.with_cores(costs.cores)  # the containers share the cores: so do the nodes
    quota = quota_costs(costs, float(args.node_cpus))
    config = SceneConfig()
    domains = Domains(store, shading_inputs(store, config, settings.integrator)[1])
    p = args.nodes
    results: list[tuple[str, bool, float, float]] = []
    with tempfile.TemporaryDirectory(prefix="compose-scale-") as tmp:
        folder = Path(tmp)
        data = folder / "data"
        data.mkdir()
        os.chmod(folder, 0o755)
        shutil.copytree(store.path, data / "store")
        reference = run([sys.executable, "-m", "vastray.cli", "render", data / "store", "-o",
                         data / "reference.exr", *render_args(settings), "--quiet"], timeout=900)
        if reference.returncode != 0:
            print(reference.stderr)
            sys.exit(1)
        if os.geteuid() != 0:  # the containers run as the data folder's owner
            os.chmod(data, 0o755)
        reference_image = read_exr(data / "reference.exr")
        print(f"\n{store.path.name}: {len(store.domains)} domains, {settings.width}x"
              f"{settings.height} px x {settings.spp} spp ({settings.paths:,} paths), "
              f"compose: {p} node containers x {args.node_cpus} CPU x 1 thread, "
              f"--cache {CACHE_PERCENT}%, on {os.cpu_count()} cores\n")
        print("| scheduler | cluster wall s | render s | real busy_max s | throttled s, most "
              "throttled node | simulated busy_max s "
              "| error | simulated, quota s | error | ray batches / node real | simulated "
              "| loads / node real | simulated | coordinator messages / node | lost nodes "
              "| image = reference |")
        print("| --- " * 16 + "|")
        for scheduler in args.schedulers.split(","):
            options = job(scheduler, p, settings, len(store.domains))
            try:
                wall, report, codes = run_cluster(client, compose, data, folder, scheduler, p,
                                                  args.node_cpus, settings)
            except (RuntimeError, OSError) as error:
                print(f"| {scheduler} | failed: {str(error).splitlines()[0]} |", flush=True)
                results.append((scheduler, False, float("nan"), float("nan")))
                continue
            image = data / "out" / "image.exr"
            if args.keep:
                args.keep.mkdir(parents=True, exist_ok=True)
                for name in (f"override-{scheduler}.yml", f"logs-{scheduler}.txt"):
                    if (folder / name).is_file():
                        shutil.copy(folder / name, args.keep / name)
                if (data / "out" / "report.json").is_file():
                    shutil.copy(data / "out" / "report.json", args.keep / f"report-{scheduler}.json")
            same = (bool(report) and not any(code for _, code in codes) and image.is_file()
                    and bool(np.array_equal(read_exr(image), reference_image)))
            if not report:
                print(f"| {scheduler} | no report.json (exit codes {codes}) |", flush=True)
                results.append((scheduler, False, float("nan"), float("nan")))
                continue
            nodes = report["counters"]["per_node"]
            batches = sum(n["counters"].get("batches_sent", 0) for n in nodes) / p
            coordinator = sum(nodes[0]["counters"].get("coordinator_messages", {}).values()) / p
            lost = len(report["counters"].get("node_failures") or [])
            busy_max = report["seconds"]["busy_max"]
            # the passes the CLI chose (one, where nothing reads the image between them)
            max_pass_spp = report["max_pass_spp"] if len(report.get("passes", [])) > 1 else None
            sim = simulate(store, options, p, shared, settings, config,
                           max_pass_spp=max_pass_spp, domains=domains)
            sim_batches = sim.counters.get("batches_sent", 0) / p
            loads = sum(n["counters"].get("loads", 0) for n in nodes) / p
            sim_loads = sim.counters.get("loads", 0) / p
            error = (sim.seconds - busy_max) / busy_max
            capped = simulate(store, options, p, quota, settings, config,
                              max_pass_spp=max_pass_spp, domains=domains).seconds
            capped_error = (capped - busy_max) / busy_max
            results.append((scheduler, same, error, capped_error))
            # the kernel's throttled time of a node's cgroup over its busy spans, over the
            # cores (``scene.cpus.cgroup_cpu_throttled_s``)
            throttled = report["counters"].get("cpu_throttled_s_max", float("nan"))
            print(f"| {scheduler} | {wall:.1f} | {report['seconds']['total']:.2f} | "
                  f"{busy_max:.2f} | {throttled:.2f} | {sim.seconds:.2f} | {error:+.0%} | {capped:.2f} | "
                  f"{capped_error:+.0%} | {batches:.1f} | "
                  f"{sim_batches:.1f} | {loads:.1f} | {sim_loads:.1f} | {coordinator:.1f} | {lost} | "
                  f"{'yes' if same else 'NO'} |", flush=True)
    domains.close()
    equal = sum(same for _, same, _, _ in results)
    print(f"\ncompose_nodes={p} compose_images_equal={equal}/{len(results)} compose_sim_error="
          + ",".join(f"{s}:{e:+.2f}" for s, _, e, _ in results)
          + " compose_sim_error_quota=" + ",".join(f"{s}:{e:+.2f}" for s, _, _, e in results)
          + f" seconds={time.perf_counter() - start:.0f}")
    sys.exit(0 if equal == len(results) else 1)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    main()
