"""Faults a cluster meets, and whether a render survives them.

For N runs of each fault, prints ``completed / identical / time overhead`` against the
fault-free render of the same frame:

- ``kill``: kill -9 of one of 4 nodes mid-frame (the frame is rendered again on the others);
- ``stop``: SIGSTOP of one of 4 nodes mid-frame (lost after ``--heartbeat-timeout``);
- ``storm``: 10,000 malformed, truncated, oversized, wrong-role and random messages sent to a
  node while it renders (dropped and counted);
- ``forged``: a forged film and a stranger's ``done`` sent to the coordinator mid-render;
- ``delay``: every message between the 2 nodes (ray batches, films, all-reduce) passes a
  ZeroMQ proxy (``fault_proxy.PeerProxy``, one per node: each node advertises its proxy's
  endpoint to its peers: each node is started through ``bench/fault_node.py --peer-endpoint``)
  that holds each a random 0-50 ms, keeping each sender's order as TCP does;
- ``drop``: the same proxies drop 1 % of the ray batches. Nothing retransmits a batch, so
  the frame cannot finish on 2 nodes: the nodes wait for it until their timeout (30 s here),
  the first to give up tells the coordinator (``failed``), and the node-loss path re-renders
  the frame on the other alone (no peer traffic left to drop), or the run fails naming the
  node when both gave up at once.

Floors: 100 % completed and identical for ``kill``, ``storm`` and ``delay``.

    python bench/faults.py [--runs 3] [--scheduler async] [--only delay drop]
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import trimesh
import zmq
from fault_node import command as fault_node_command
from fault_proxy import PeerProxy

from vastray.actors import protocol
from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.render.integrators import RenderSettings
from vastray.scene.partition import partition_kd
from vastray.scene.store import DomainArrays, Store, StoreWriter
from vastray.transport.codec import encode

#: The share of ray batches the ``drop`` fault's proxies drop.
DROP_FRACTION = 0.01

SCENE_TOML = """
[camera]
position = [3.0, 2.2, 4.5]
look_at = [0.0, -0.5, 0.0]
[[light]]
type = "point"
position = [2.0, 3.0, 1.0]
intensity = 12.0
"""


def make_scene(root: Path) -> tuple[Path, Path]:
    sphere = trimesh.creation.icosphere(subdivisions=4)
    ground = trimesh.creation.box(extents=[6.0, 0.1, 6.0])
    ground.apply_translation([0, -1.3, 0])
    mesh = trimesh.util.concatenate([sphere, ground])
    arrays = DomainArrays(np.asarray(mesh.vertices, np.float32),
                          np.asarray(mesh.faces, np.uint32))
    with StoreWriter(root / "s.store") as writer:
        for dom in partition_kd(arrays, 8).domains:
            writer.add_domain(dom)
    (root / "scene.toml").write_text(SCENE_TOML)
    return root / "s.store", root / "scene.toml"


def child_nodes(rank: int) -> list[int]:
    """Pids of this process's node children with ``rank``."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
            parent = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        if parent == os.getpid() and b"--rank" in cmd and \
                cmd[cmd.index(b"--rank") + 1] == str(rank).encode():
            found.append(int(proc.name))
    return found


def signal_run(store, toml, settings, scheduler, sig) -> tuple[object, float]:
    """4 nodes started here; node 2 gets ``sig`` a second into its work (None: no fault)."""
    hit = []

    def strike():
        deadline = time.monotonic() + 30
        while sig is not None and time.monotonic() < deadline and not hit:
            pids = child_nodes(2)
            if pids:
                time.sleep(1.0)
                for pid in pids:
                    os.kill(pid, sig)
                hit.extend(pids)
            time.sleep(0.1)

    striker = threading.Thread(target=strike)
    striker.start()
    start = time.perf_counter()
    try:
        result = render_distributed(store, toml, settings, 4,
                                    options=JobOptions(scheduler=scheduler, max_samples_in_flight=300),
                                    timeout=60, heartbeat_timeout=5.0)
    finally:
        striker.join()
    return result, time.perf_counter() - start


def storm_run(store, toml, settings, scheduler, fault: str | None,
              seed: int = 0) -> tuple[object, float]:
    """Nodes started as `vastray node`; mid-render, node 0 gets the storm (``"storm"``) or the
    coordinator a forged film and done (``"forged"``); or from the start, every node's peers
    send to it through a ``PeerProxy`` that delays (``"delay"``) or drops (``"drop"``)
    messages; None: no fault (the baseline)."""
    port = free_port()
    logs = Path(tempfile.mkdtemp(prefix="vastray-faults-"))
    nodes, proxies = [], []
    # proxied runs: shorter waits, so that a run that hangs on lost messages ends in minutes
    timeout, heartbeat = (30.0, 5.0) if fault in ("delay", "drop") else (60.0, None)
    for i in range(2):
        peer_endpoint = None
        if fault in ("delay", "drop"):
            proxy_port = free_port()
            peer_endpoint = f"tcp://127.0.0.1:{proxy_port}"
            proxies.append(PeerProxy(proxy_port, logs / f"n{i}.log", fault, seed=seed + i,
                                     drop_fraction=DROP_FRACTION))
            proxies[-1].start()
        with open(logs / f"n{i}.log", "wb") as err:
            nodes.append(subprocess.Popen(
                fault_node_command(["--coordinator", f"tcp://127.0.0.1:{port}",
                                    "--timeout", str(timeout)], peer_endpoint=peer_endpoint),
                stdout=subprocess.DEVNULL, stderr=err))
    outcome = {}

    def run():
        start = time.perf_counter()
        try:
            outcome["result"] = render_distributed(store, toml, settings, 2,
                                                   options=JobOptions(scheduler=scheduler,
                                                                      max_samples_in_flight=2000),
                                                   listen=f"127.0.0.1:{port}", timeout=timeout,
                                                   heartbeat_timeout=heartbeat)
        except Exception as exc:  # noqa: BLE001 - reported by the caller
            outcome["error"] = exc
        outcome["seconds"] = time.perf_counter() - start

    thread = threading.Thread(target=run)
    thread.start()
    ctx = zmq.Context()
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not all(
                "joined" in (logs / f"n{i}.log").read_text() for i in range(2)):
            time.sleep(0.05)
        rng = np.random.default_rng(0)
        if fault in (None, "delay", "drop"):
            pass
        elif fault == "forged":
            sock = ctx.socket(zmq.DEALER)
            sock.connect(f"tcp://127.0.0.1:{port}")
            n = settings.width * settings.height
            film = encode(protocol.FILM, {"sum": np.full((n, 3), 1e6), "sum_odd": np.zeros((n, 3)),
                                          "count": np.ones(n, np.int64),
                                          "depth": np.zeros(n, np.float32),
                                          "normal": np.zeros((n, 3), np.float32)}, {"rank": 0})
            done = encode(protocol.DONE, {}, {"rank": 0, "busy_s": 0.0, "reduce_s": 0.0,
                                              "counters": {}})
            for frames in (film, done):
                sock.send_multipart([b"", *frames])
        else:
            endpoint = re.search(r"listening for peers on (tcp://\S+)",
                                 (logs / "n0.log").read_text()).group(1)
            sock = ctx.socket(zmq.DEALER)
            sock.setsockopt(zmq.SNDHWM, 0)
            sock.connect(endpoint)
            for i in range(10_000):
                kind = ["rays", "film", "job", "x" * 70, "reduce"][i % 5]
                frames = (encode(kind, {"domain": np.zeros(i % 7, np.int64)}, {"rank": i})
                          if i % 3 else [rng.bytes(int(rng.integers(0, 64)))])
                sock.send_multipart([rng.bytes(16) if i % 2 else b"", *frames])
        thread.join(timeout=300)
    finally:
        for node in nodes:
            if node.poll() is None:
                node.kill()
            node.wait()
        for proxy in proxies:
            proxy.stop()
        ctx.destroy(linger=0)
    if proxies:
        lost = outcome["result"].counters["node_failures"] if "result" in outcome else []
        print(f"  {fault}: the proxies forwarded {sum(p.forwarded for p in proxies)} peer "
              f"messages and dropped {sum(p.dropped for p in proxies)} ray batches; "
              f"{outcome.get('seconds', float('nan')):.1f} s"
              + "".join(f"; lost {failure}" for failure in lost), file=sys.stderr)
    if "error" in outcome:
        raise outcome["error"]
    if "result" not in outcome:
        raise RuntimeError("the render did not complete")
    return outcome["result"], outcome["seconds"]


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--only", nargs="+", metavar="FAULT",
                        choices=["kill", "stop", "storm", "forged", "delay", "drop"],
                        help="run only these faults (the baselines always run)")
    parser.add_argument("--scheduler", default="async",
                        choices=["image", "spec-ooc", "domain", "async", "spec-insitu"])
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="vastray-faults-"))
    store, toml = make_scene(root)
    settings = RenderSettings(width=32, height=24, spp=32, integrator="pt", bounces=2,
                              shadow_samples=4)
    render_distributed(store, toml, settings, 2, options=JobOptions(scheduler=args.scheduler),
                       timeout=60)  # warm-up
    # The fault-free runs each fault is compared with, started the same way as the faulty ones:
    # 4 nodes started by the coordinator (kill, stop), 2 started as `vastray node` (storm,
    # forged); the median of --runs.
    kinds = {"local": lambda: signal_run(store, toml, settings, args.scheduler, None),
             "external": lambda: storm_run(store, toml, settings, args.scheduler, None)}
    clean_s, reference = {}, None
    for kind, run in kinds.items():
        times = []
        for _ in range(args.runs):
            result, seconds = run()
            times.append(seconds)
            reference = result.film.image() if reference is None else reference
        clean_s[kind] = float(np.median(times))
    print(f"scene: {Store(store).n_triangles:,} triangles in 8 domains; {args.scheduler}, "
          f"pt {settings.width}x{settings.height} {settings.spp} spp; fault-free median "
          f"{clean_s['local']:.2f} s on 4 nodes started here (kill, stop), "
          f"{clean_s['external']:.2f} s on 2 nodes started as `vastray node` (storm, forged)\n")
    print("| fault | runs | completed | identical | time overhead (median) |")
    print("| --- | --- | --- | --- | --- |")
    faults = {
        "kill": ("local", lambda: signal_run(store, toml, settings, args.scheduler,
                                             signal.SIGKILL)),
        "stop": ("local", lambda: signal_run(store, toml, settings, args.scheduler,
                                             signal.SIGSTOP)),
        "storm": ("external", lambda: storm_run(store, toml, settings, args.scheduler, "storm")),
        "forged": ("external", lambda: storm_run(store, toml, settings, args.scheduler,
                                                 "forged")),
        "delay": ("external", lambda i: storm_run(store, toml, settings, args.scheduler,
                                                  "delay", seed=10 * i)),
        "drop": ("external", lambda i: storm_run(store, toml, settings, args.scheduler,
                                                 "drop", seed=10 * i)),
    }
    for name, (baseline, run) in faults.items():
        if args.only and name not in args.only:
            continue
        completed = identical = 0
        overheads = []
        for i in range(args.runs):
            try:
                result, seconds = run(i) if name in ("delay", "drop") else run()
            except Exception as exc:  # noqa: BLE001 - a failed run is a data point
                print(f"  {name}: failed: {exc}", file=sys.stderr)
                continue
            completed += 1
            identical += bool(np.allclose(result.film.image(), reference, rtol=1e-6,
                                          atol=1e-6))
            overheads.append(seconds / clean_s[baseline])
        overhead = f"{np.median(overheads):.2f}x" if overheads else "-"
        print(f"| {name} | {args.runs} | {100 * completed / args.runs:.0f} % | "
              f"{100 * identical / args.runs:.0f} % | {overhead} |", flush=True)


if __name__ == "__main__":
    main()
