"""Distributed rendering and transport throughput.

1. Ray batches through the codec and ZeroMQ (msgpack header + raw frames, zero-copy) against
   raw ZeroMQ multipart messages of the same bytes, over loopback TCP between two processes:
   ``transport_ratio=`` (floor 0.8) against one raw frame per array. The codec side is the
   member path as nodes run it: frames up to ``PEER_FRAME_LIMIT``, sent on a ROUTER with a
   node's peer-port options to a DEALER that connected to it. The clock starts after a
   warm-up round trip (the
   receiver process is up and connected) and stops when the receiver has taken the last
   message, so process start-up and teardown are in neither timing.
2. N = 1, 2, 4 local node processes with every distributed scheduler at an equal memory
   budget: each node may hold ceil(D / N) domains, the share ``spec-insitu`` keeps resident
   (it ignores --cache), so every scheduler holds as many domains as the others. Time, rays
   and bytes sent, loads, threads per node, and each scheduler's time ratio against
   ``async`` (the Galaxy-style baseline of the temporal-coherence paper). Each render is timed
   as ``vastray render --nodes N`` runs it (``vastray.render``: the CLI's plan, its passes
   included: one pass out of core when nothing reads the image between passes, else 1, 1,
   2, 4, ... spp), and the runtime's one-pass render (``render_distributed``) beside it.

    python bench/distributed.py [--quick]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np
import zmq

import vastray
from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.actors.management import routing_id
from vastray.render.integrators import RenderSettings
from vastray.scene.generate import generate
from vastray.scene.store import Store
from vastray.schedule import registry
from vastray.schedule.registry import Option
from vastray.transport.codec import PEER_FRAME_LIMIT, decode, encode
from vastray.transport.security import FRAME_OVERHEAD, bound

CACHE = Path(__file__).resolve().parent.parent / ".bench_cache"


def ray_batch(n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {"origin": rng.random((n, 3), dtype=np.float32),
            "direction": rng.random((n, 3), dtype=np.float32),
            "t_max": rng.random(n, dtype=np.float32),
            "beta": rng.random((n, 3), dtype=np.float32),
            "pixel": rng.integers(0, 1 << 24, n).astype(np.uint32),
            "sample": rng.integers(0, 64, n).astype(np.uint32),
            "depth": rng.integers(0, 4, n).astype(np.uint8),
            "kind": rng.integers(0, 2, n).astype(np.uint8)}


def _receiver(endpoint: str, reply: str, messages: int, codec: bool) -> None:
    ctx = zmq.Context()
    if codec:  # a node's socket for one peer: connects to the peer, takes large frames
        sock = ctx.socket(zmq.DEALER)
        bound(sock)
        sock.setsockopt(zmq.MAXMSGSIZE, PEER_FRAME_LIMIT + FRAME_OVERHEAD)
        sock.setsockopt(zmq.ROUTING_ID, routing_id(TOKEN))
    else:
        sock = ctx.socket(zmq.PULL)
    sock.connect(endpoint)
    back = ctx.socket(zmq.PUSH)
    back.connect(reply)
    sock.recv_multipart(copy=False)  # the warm-up message
    back.send(b"ready")
    for _ in range(messages):
        frames = sock.recv_multipart(copy=False)
        if codec:
            decode(frames[1:])  # behind the pair's token, as a node takes it
    back.send(b"done")
    ctx.destroy(linger=1000)


#: The pair token of the codec side's two "nodes".
TOKEN = b"t" * 16


def transport(n_rays: int, messages: int) -> tuple[float, float]:
    """Rays per second through raw multipart frames (PUSH to PULL, one frame per array, no
    frame limit) and through the member path (the codec with ``PEER_FRAME_LIMIT``, from a
    ROUTER with a node's peer-port options to a DEALER that connected to it, behind the
    pair's token), timed from after a warm-up round trip to the receiver's acknowledgement of
    the last message."""
    batch = ray_batch(n_rays)
    raw_frames = [np.ascontiguousarray(a).data for a in batch.values()]
    rates = []
    for codec in (False, True):
        ctx = zmq.Context()
        if codec:
            sock = ctx.socket(zmq.ROUTER)
            bound(sock)
            sock.setsockopt(zmq.ROUTER_MANDATORY, 1)
        else:
            sock = ctx.socket(zmq.PUSH)
            sock.setsockopt(zmq.SNDHWM, 64)
        port = sock.bind_to_random_port("tcp://127.0.0.1")
        replies = ctx.socket(zmq.PULL)
        reply_port = replies.bind_to_random_port("tcp://127.0.0.1")
        proc = mp.get_context("spawn").Process(
            target=_receiver, args=(f"tcp://127.0.0.1:{port}", f"tcp://127.0.0.1:{reply_port}",
                                    messages, codec))
        proc.start()

        def frames(codec: bool = codec) -> list:
            if not codec:
                return raw_frames
            return [routing_id(TOKEN), TOKEN, *encode("rays", batch, {"rank": 1},
                                                      PEER_FRAME_LIMIT)]

        deadline = time.monotonic() + 60
        while True:  # the ROUTER refuses until the receiver has connected
            try:
                sock.send_multipart(frames(), copy=False)
                break
            except zmq.ZMQError as exc:
                if exc.errno != zmq.EHOSTUNREACH or time.monotonic() > deadline:
                    raise
                time.sleep(0.01)
        if not replies.poll(60_000):
            raise TimeoutError("the receiver process did not start within 60 s")
        assert replies.recv() == b"ready"
        start = time.perf_counter()
        for _ in range(messages):
            sock.send_multipart(frames(), copy=False)
        if not replies.poll(120_000):
            raise TimeoutError("the receiver did not take every message within 120 s")
        assert replies.recv() == b"done"
        rates.append(n_rays * messages / (time.perf_counter() - start))
        proc.join()
        ctx.destroy(linger=0)
    return rates[0], rates[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    runs = [transport(65536, 100 if args.quick else 400) for _ in range(5)]
    ratios = sorted(codec / raw for raw, codec in runs)
    raw, codec = (float(np.median(side)) for side in zip(*runs, strict=True))
    print(f"raw_zmq_rays_per_s={raw:,.0f} codec_zmq_rays_per_s={codec:,.0f}  (medians of "
          f"{len(runs)} runs)")
    print(f"transport_ratio={ratios[len(ratios) // 2]:.3f}  (median of {len(runs)} runs, "
          f"{ratios[0]:.3f} to {ratios[-1]:.3f}; raw: one frame per array, no frame limit; "
          "codec: the member path, ROUTER to a connected DEALER)", flush=True)

    resolution = 160 if args.quick else 320
    path = CACHE / f"rm-{resolution}-4x4x2.store"
    if not (path / "manifest.json").is_file():
        generate("rm", path, resolution, grid=(4, 4, 2), seed=0, overwrite=True)
    store = Store(path)
    settings = RenderSettings(width=48, height=36, spp=4 if args.quick else 8, integrator="pt",
                              bounces=2, shadow_samples=4)
    print(f"\nscene: {store.n_triangles:,} triangles in {len(store.domains)} domains, "
          f"pt {settings.width}x{settings.height} {settings.spp} spp; each node may hold "
          "ceil(domains / N) domains (spec-insitu's resident share: equal memory)\n")
    print("| scheduler | nodes | cache per node | threads per node | CLI s (passes) | one-pass s "
          "| rays sent | MB sent | loads (all nodes) | busiest node s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    schedulers = ("async", "domain", "dynamic", "spec-insitu", "image", "spec-ooc")
    times, one_pass = {}, {}
    for nodes in (1, 2, 4):
        cache = -(-len(store.domains) // nodes)
        for scheduler in schedulers:
            # as `vastray render --nodes N` runs it (passes where its plan keeps them)
            start = time.perf_counter()
            # spec-insitu keeps its own domains resident: --cache does not apply to it
            cli_cache = cache if registry.spec(scheduler).accepts(Option.CACHE) else None
            out = vastray.render(path, nodes=nodes, scheduler=scheduler, cache=cli_cache,
                                 max_samples_in_flight=1024, width=settings.width,
                                 height=settings.height, spp=settings.spp, integrator="pt",
                                 bounces=settings.bounces,
                                 shadow_samples=settings.shadow_samples, progress=False)
            cli_s = time.perf_counter() - start
            # the runtime's one pass, beside it
            result = render_distributed(path, None, settings, nodes,
                                        options=JobOptions(scheduler=scheduler, cache=cache,
                                                           max_samples_in_flight=1024))
            per_node = [n["counters"] for n in out.report["counters"]["per_node"]]
            rays = sum(c.get("rays_sent", 0) for c in per_node)
            megabytes = sum(c.get("bytes_sent", 0) for c in per_node) / 1e6
            loads = sum(c.get("loads", 0) for c in per_node)
            threads = per_node[0].get("threads", 1)
            times[scheduler, nodes] = cli_s
            one_pass[scheduler, nodes] = result.seconds["total"]
            print(f"| {scheduler} | {nodes} | {cache} | {threads} | "
                  f"{cli_s:.2f} ({len(out.report['passes'])}) | {result.seconds['total']:.2f} "
                  f"| {rays:,} | {megabytes:.1f} | {loads} "
                  f"| {out.report['seconds']['busy_max']:.2f} |", flush=True)
    for nodes in (1, 2, 4):
        ratios = " ".join(f"{s}={times['async', nodes] / times[s, nodes]:.2f}"
                          for s in schedulers if s != "async")
        print(f"nodes={nodes} time ratio vs async (async s / scheduler s, CLI path): {ratios}")
        ratios = " ".join(f"{s}={one_pass['async', nodes] / one_pass[s, nodes]:.2f}"
                          for s in schedulers if s != "async")
        print(f"nodes={nodes} one-pass time ratio vs async: {ratios}")


if __name__ == "__main__":
    main()
