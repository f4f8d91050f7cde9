"""What fresh processes measure: ``python -m vastray.sim.warmup STORE`` renders the
calibration's node image out of core (the ``image`` schedule: scene set-up, every domain
loaded and its BVH built, the tile traced, the film filled) once untimed (its first use paid),
prints "ready", waits for a line on its input, renders it ``--repeat`` times more and prints,
as JSON, the later renders' mean seconds (``render_s``). Started k at a time and told to go
together, the later renders run side by side: the machine's throughput with k busy
processes. (A node's first use is measured on real nodes: ``vastray.sim.node_cost``.)"""

from __future__ import annotations

import json
import select
import subprocess
import sys
import time

import numpy as np

from vastray.scene.errors import InputError

#: Seconds a measuring process may take (it starts Python, imports, renders a few times).
PROCESS_TIMEOUT_S = 300.0


def measure_processes(store_path: str, quick: bool, count: int) -> list[dict]:
    """``count`` fresh processes whose later renders run side by side (each says "ready"
    after its first render, and all are told to go together); each one's ``{"warmup_s",
    "render_s"}``."""
    command = [sys.executable, "-m", "vastray.sim.warmup", str(store_path), "--repeat",
               "2" if quick else "3"] + (["--quick"] if quick else [])
    processes = [subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True) for _ in range(count)]
    try:
        deadline = time.monotonic() + PROCESS_TIMEOUT_S
        for process in processes:
            ready, _, _ = select.select([process.stdout], [], [],
                                        max(0.0, deadline - time.monotonic()))
            if not ready or process.stdout.readline().strip() != "ready":
                raise RuntimeError(_failure(process, "did not get ready"))
        for process in processes:
            process.stdin.write("go\n")
            process.stdin.flush()
        results = []
        for process in processes:
            out, _ = process.communicate(timeout=max(1.0, deadline - time.monotonic()))
            if process.returncode != 0:
                raise RuntimeError(_failure(process, "failed"))
            results.append(json.loads(out))
        return results
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"a calibration process took over {PROCESS_TIMEOUT_S:.0f} s") from None
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.wait()


def _failure(process: subprocess.Popen, what: str) -> str:
    if process.poll() is None:
        process.kill()
    _, err = process.communicate()
    return f"a calibration process {what}: {err.strip().splitlines()[-1:] or process.returncode}"


def process_costs(store_path: str, quick: bool, cores: int) -> tuple[float, ...]:
    """The aggregate throughput with k = 1 .. 2 x ``cores`` processes side by side, in
    single-process speeds (quick: k = 1, cores, 2 x cores, the rest interpolated)."""
    counts = sorted({1, cores, 2 * cores}) if quick else list(range(1, 2 * cores + 1))
    alone = measure_processes(store_path, quick, 1)[0]
    measured = {1: 1.0}
    for k in counts[1:]:
        runs = measure_processes(store_path, quick, k)
        measured[k] = k * alone["render_s"] / (sum(r["render_s"] for r in runs) / k)
    known = sorted(measured)
    throughput = np.interp(np.arange(1, known[-1] + 1), known, [measured[k] for k in known])
    return tuple(float(t) for t in throughput)


def main(argv: list[str]) -> int:
    import argparse

    from vastray.actors.job_options import JobOptions
    from vastray.actors.local import render_out_of_core
    from vastray.render.scene_config import SceneConfig
    from vastray.scene.store import Store
    from vastray.sim.calibrate import calibration_settings, node_settings

    parser = argparse.ArgumentParser(prog="python -m vastray.sim.warmup")
    parser.add_argument("store")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    store = Store(args.store)
    # twice the calibration tile (about 0.4 s here): long enough for the processes' renders
    # to run side by side
    settings = node_settings(calibration_settings(args.quick))

    def render() -> float:
        start = time.perf_counter()
        render_out_of_core(store, SceneConfig(text=""), settings, JobOptions(scheduler="image"),
                           progress=False)
        return time.perf_counter() - start

    render()  # first use: not timed
    print("ready", flush=True)
    sys.stdin.readline()  # "go": every process renders from here, side by side
    later = [render() for _ in range(args.repeat)]
    mean = sum(later) / len(later)
    print(json.dumps({"render_s": mean}))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv[1:]))
    except InputError as exc:
        sys.exit(f"vastray.sim.warmup: {exc}")
