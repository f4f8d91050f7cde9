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

- ``memory``: an outsider (``bench/fault_attacker.py``: none of the render's credentials)
  tries to make a node and the coordinator hold memory while they wait for the job: 3 ZeroMQ
  messages of one 900 MB frame (no secret, then a wrong one), one 900 MB frame over raw TCP
  after a greeting, and 3 TCP connections each holding half of a declared 900 MB frame
  (2,000 MB against the coordinator); and a flood of ``FLOOD_CONNECTIONS`` raw connections that
  each send the largest handshake frame a socket takes, all but its last byte, and hold on.
  Prints the peak growth of the target's resident memory during each attack (sampled every
  10 ms) against ``MEMORY_BOUND_MB`` (``FLOOD_BOUND_MB`` for the flood; the flood's figures
  again as ``preauth_flood_mb=node:X,coordinator:Y``); then the render goes on and must give
  the fault-free image.

Floors: 100 % completed and identical for ``kill``, ``storm`` and ``delay``; every ``memory``
attack within its bound.

    python bench/faults.py [--runs 3] [--scheduler async] [--only delay drop memory]
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
from vastray.processes import proc_bytes
from vastray.render.film import BATCHES, CHANNELS
from vastray.render.integrators import RenderSettings
from vastray.scene.partition import partition_kd
from vastray.scene.store import DomainArrays, Store, StoreWriter
from vastray.transport.codec import FRAME_LIMIT, encode
from vastray.transport.join_secret import read_join_secret

#: The share of ray batches the ``drop`` fault's proxies drop.
DROP_FRACTION = 0.01

#: Most megabytes an outsider may make a node or the coordinator hold (``memory``): the
#: largest frame a socket takes before the handshake, 4 MiB, with room for ZeroMQ's buffers.
MEMORY_BOUND_MB = 16
#: Raw connections of the ``raw-flood`` attack, and the most they may make a target hold (each
#: may hold a frame until its handshake times out: ``transport.doorkeeper`` bounds how many).
FLOOD_CONNECTIONS = 1000
FLOOD_BOUND_MB = 64

ATTACKER = Path(__file__).with_name("fault_attacker.py")

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
            proxies.append(PeerProxy(proxy_port, logs / f"n{i}.log", fault, port,
                                     seed=seed + i, drop_fraction=DROP_FRACTION))
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
        elif fault == "forged":  # from a process of this user: it holds the join secret
            sock = ctx.socket(zmq.DEALER)
            sock.plain_username, sock.plain_password = b"vastray", read_join_secret(port, 10)
            sock.connect(f"tcp://127.0.0.1:{port}")
            n = settings.width * settings.height
            film = encode(protocol.FILM, {"sum": np.full((n, 3), 1e6),
                                          "batch": np.zeros((n, BATCHES, CHANNELS)),
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
            sock.plain_username, sock.plain_password = b"vastray", read_join_secret(port, 10)
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


def rss_bytes(pid: int) -> int:
    rss = proc_bytes(f"/proc/{pid}/status", "VmRSS")
    if rss is None:
        raise RuntimeError(f"no VmRSS for pid {pid} (it exited?)")
    return rss


def attack_growth(pid: int, endpoint: str, attack: str, frame_mb: int) -> tuple[int, str]:
    """Run one attack on ``endpoint`` (the socket of process ``pid``) and return the peak
    growth of that process's resident memory while it lasted, and what the attacker said."""
    base = rss_bytes(pid)
    attacker = subprocess.Popen([sys.executable, str(ATTACKER), endpoint, attack,
                                 "--frame-mb", str(frame_mb), "--hold", "2",
                                 "--connections", str(FLOOD_CONNECTIONS if attack == "raw-flood"
                                                      else 3)],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    peak = base
    while attacker.poll() is None:
        peak = max(peak, rss_bytes(pid))
        time.sleep(0.01)
    peak = max(peak, rss_bytes(pid))
    return peak - base, attacker.stdout.read().strip()


def memory_run(store, toml, settings, scheduler: str) -> tuple[object, list[tuple]]:
    """Three nodes of which two join at once: while the coordinator waits for the third and
    the two wait for their job, every attack is made on node 0's peer port and on the
    coordinator; then the third node joins and the render runs. Returns the result and one
    row (attack, target, frame MB, growth bytes, attacker's words) per attack."""
    port = free_port()
    logs = Path(tempfile.mkdtemp(prefix="vastray-memory-"))
    outcome, nodes = {}, []

    def run():
        try:
            outcome["result"] = render_distributed(
                store, toml, settings, 3, options=JobOptions(scheduler=scheduler),
                listen=f"127.0.0.1:{port}", timeout=120)
        except Exception as exc:  # noqa: BLE001 - reported by the caller
            outcome["error"] = exc

    def start_node(i: int) -> None:
        with open(logs / f"n{i}.log", "wb") as err:
            nodes.append(subprocess.Popen(
                [sys.executable, "-m", "vastray.cli", "node", "--coordinator",
                 f"tcp://127.0.0.1:{port}", "--timeout", "120"],
                stdout=subprocess.DEVNULL, stderr=err))

    thread = threading.Thread(target=run)
    thread.start()
    rows = []
    try:
        for i in range(2):
            start_node(i)
        deadline = time.monotonic() + 60
        endpoint = None
        while endpoint is None and time.monotonic() < deadline:
            found = re.search(r"listening for peers on (tcp://\S+)",
                              (logs / "n0.log").read_text())
            endpoint = found.group(1) if found else None
            time.sleep(0.05)
        time.sleep(2.0)  # both said hello; they wait for the job, the coordinator for node 3
        targets = [("node", nodes[0].pid, endpoint, 900),
                   ("coordinator", os.getpid(), f"tcp://127.0.0.1:{port}", 2000)]
        for target, pid, where, frame_mb in targets:
            for attack in ("zmq-frames", "zmq-wrong-secret", "raw-frame", "raw-partial",
                           "raw-flood"):
                growth, said = attack_growth(pid, where, attack, frame_mb)
                rows.append((attack, target, frame_mb, growth, said))
        start_node(2)
        thread.join(timeout=300)
    finally:
        thread.join(timeout=300)
        for node in nodes:
            if node.poll() is None:
                node.kill()
            node.wait()
    if "error" in outcome:
        raise outcome["error"]
    return outcome["result"], rows


def print_memory_table(rows: list[tuple]) -> bool:
    """The ``memory`` table; True when every attack stayed within its bound."""
    print("\n| attack | target | frame | peak RSS growth | bound | within |")
    print("| --- | --- | --- | --- | --- | --- |")
    ok = True
    for attack, target, frame_mb, growth, _ in rows:
        flood = attack == "raw-flood"
        bound = FLOOD_BOUND_MB if flood else MEMORY_BOUND_MB
        within = growth <= bound * 1_000_000
        ok &= within
        frame = (f"{FLOOD_CONNECTIONS:,} x {FRAME_LIMIT >> 10} KiB" if flood
                 else f"{frame_mb:,} MB")
        print(f"| {attack} | {target} | {frame} | {growth / 1e6:.1f} MB | "
              f"{bound} MB | {'yes' if within else 'NO'} |", flush=True)
    flood = {target: growth for attack, target, _, growth, _ in rows if attack == "raw-flood"}
    print("preauth_flood_mb=" + ",".join(f"{t}:{g / 1e6:.1f}" for t, g in flood.items()))
    return ok


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--only", nargs="+", metavar="FAULT",
                        choices=["kill", "stop", "storm", "forged", "delay", "drop", "memory"],
                        help="run only these faults (the baselines run for any but memory)")
    parser.add_argument("--scheduler", default="async",
                        choices=["image", "spec-ooc", "domain", "async", "spec-insitu"])
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="vastray-faults-"))
    store, toml = make_scene(root)
    settings = RenderSettings(width=32, height=24, spp=32, integrator="pt", bounces=2,
                              shadow_samples=4)
    render_distributed(store, toml, settings, 2, options=JobOptions(scheduler=args.scheduler),
                       timeout=60)  # warm-up
    if args.only == ["memory"]:
        from vastray.render.driver import render
        from vastray.render.scene_config import load_scene_config

        reference = render(Store(store), load_scene_config(toml), settings,
                           progress=False).film.image()
        return memory_section(store, toml, settings, args.scheduler, reference)
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
    if not args.only or "memory" in args.only:
        return memory_section(store, toml, settings, args.scheduler, reference)
    return 0


def memory_section(store, toml, settings, scheduler: str, reference: np.ndarray) -> int:
    """The ``memory`` attacks, their table and the render's verdict; 1 if any failed."""
    result, rows = memory_run(store, toml, settings, scheduler)
    ok = print_memory_table(rows)
    identical = bool(np.allclose(result.film.image(), reference, rtol=1e-6, atol=1e-6))
    refused = sum(r["counters"].get("refused_connections", 0)
                  for r in result.counters["per_node"])
    print(f"\nmemory: the render after the attacks is {'identical' if identical else 'NOT '}"
          f"{'' if identical else 'identical'}; refused connections: node reports {refused}, "
          f"coordinator "
          f"{result.counters['per_node'][0]['counters'].get('coordinator_refused_connections')}")
    return 0 if ok and identical else 1


if __name__ == "__main__":
    sys.exit(main())
