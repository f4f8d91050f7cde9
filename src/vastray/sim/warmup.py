"""The machine's throughput with k busy processes, measured by warm processes rendering side
by side: ``python -m vastray.sim.warmup STORE`` renders the calibration's node image out of
core (the ``image`` schedule, one thread: scene set-up, every domain loaded and its BVH built,
the tile traced, the film filled) once untimed (its first use paid), prints "ready", then
renders once for every "go" line on its input, printing each render's CPU seconds as JSON
(``cpu_s``, the process's own, all its threads), until its input ends. (A node's first use is
measured on real nodes: ``vastray.sim.node_cost``.)

``process_costs`` starts 4 x cores such processes once and, round after round, tells 1, then 2,
... of them to go together (4 x cores because a validation runs 8 node processes on 2 cores,
and 8 processes measured 1.64 where 4 measured 1.77, session 35): every process count is
measured in every round, and medians over the rounds make the ratio. What the ratio measures is
contention, from CPU seconds: k processes side by side run ``min(k, cores)`` at a time, each
needing more CPU per render than one alone where they compete for caches and memory. Wall
seconds would also count the time the host gave our cores to other virtual machines ("steal",
``sim.steal``), which moves from none to a third within minutes here and is measured apart,
beside each real run it slows. (Measured once per count by fresh processes, one count after
another, in wall seconds, four calibrations gave 1.54 to 2.15 for 4 processes on 2 cores, and
every multi-process validation row moved with it.)"""

from __future__ import annotations

import json
import select
import subprocess
import sys
import tempfile
import time

import numpy as np

from vastray.scene.errors import InputError

#: Seconds a measuring process may take to get ready (it starts Python, imports, renders once).
PROCESS_TIMEOUT_S = 300.0
#: Seconds one side-by-side render may take.
RENDER_TIMEOUT_S = 120.0
#: Rounds of measurements (every process count in each).
ROUNDS = 5
ROUNDS_QUICK = 3


class WarmProcesses:
    """``count`` warm measuring processes (``python -m vastray.sim.warmup``), each ready to
    render on "go"; closed (their input ended, killed if need be) by ``close``."""

    def __init__(self, store_path: str, quick: bool, count: int, tile: bool = False):
        command = [sys.executable, "-m", "vastray.sim.warmup", str(store_path)] + (
            ["--quick"] if quick else []) + (["--tile"] if tile else [])
        self.processes: list[subprocess.Popen] = []
        self.errors: list = []
        try:
            for _ in range(count):
                # stderr to a file, not a pipe: a long-lived process writing more than a
                # pipe holds would block (read back only to say why one failed)
                self.errors.append(tempfile.TemporaryFile("w+"))
                self.processes.append(subprocess.Popen(
                    command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                    stderr=self.errors[-1], text=True))
            deadline = time.monotonic() + PROCESS_TIMEOUT_S
            for process in self.processes:
                if self._line(process, deadline) != "ready":
                    raise RuntimeError(self._failure(process, "did not get ready"))
        except BaseException:
            self.close()
            raise

    @staticmethod
    def _line(process: subprocess.Popen, deadline: float) -> str | None:
        ready, _, _ = select.select([process.stdout], [], [],
                                    max(0.0, deadline - time.monotonic()))
        return process.stdout.readline().strip() if ready else None

    def render(self, k: int) -> list[float]:
        """The first ``k`` processes render once, told to go together: each one's CPU
        seconds."""
        chosen = self.processes[:k]
        for process in chosen:
            process.stdin.write("go\n")
            process.stdin.flush()
        deadline = time.monotonic() + RENDER_TIMEOUT_S
        seconds = []
        for process in chosen:
            line = self._line(process, deadline)
            if not line:
                raise RuntimeError(self._failure(process, f"gave no render time in "
                                                          f"{RENDER_TIMEOUT_S:.0f} s"))
            seconds.append(float(json.loads(line)["cpu_s"]))
        return seconds

    def _failure(self, process: subprocess.Popen, what: str) -> str:
        """Why ``process`` failed: the last line of its error output (it is killed)."""
        if process.poll() is None:
            process.kill()
        process.wait()
        errors = self.errors[self.processes.index(process)]
        errors.seek(0)
        last = errors.read().strip().splitlines()[-1:]
        return f"a calibration process {what}: {last[0] if last else process.returncode}"

    def close(self) -> None:
        """End every process (its input closed; killed after 10 s) and close its files."""
        for process in self.processes:
            if process.poll() is None:
                try:
                    process.stdin.close()
                    process.wait(timeout=10)
                except (OSError, subprocess.TimeoutExpired):
                    process.kill()
                    process.wait()
        for process in self.processes:
            for stream in (process.stdin, process.stdout):
                if stream is not None and not stream.closed:
                    stream.close()
        for errors in self.errors:  # one more than the processes if a start failed
            errors.close()


def throughput_of(rounds: list[dict[int, list[float]]], cores: int) -> dict[int, float]:
    """Aggregate throughput per process count, in single-process speeds, from ``rounds`` of
    side-by-side renders' CPU seconds (each round: process count -> each process's CPU
    seconds; count 1 in every round): ``min(k, cores)`` processes run at a time, each at the
    median alone render's CPU over the median of the rounds' mean CPU with k (contention),
    at most ``min(k, cores)`` (a ratio above 1 is noise)."""
    alone = float(np.median([r[1][0] for r in rounds]))
    out = {}
    for k in sorted(rounds[0]):
        together = float(np.median([np.mean(r[k]) for r in rounds]))
        running = float(min(k, cores))
        out[k] = running * min(1.0, alone / together)
    return out


def measure_rounds(processes: WarmProcesses, counts: list[int],
                   rounds: int) -> list[dict[int, list[float]]]:
    """``rounds`` rounds of side-by-side renders, every count of ``counts`` in each, each round
    in another order (so no count always follows the same one)."""
    out = []
    for index in range(rounds):
        order = counts[index % len(counts):] + counts[:index % len(counts)]
        out.append({k: processes.render(k) for k in order})
    return out


def interpolated(measured: dict[int, float]) -> tuple[float, ...]:
    """``measured`` (count -> throughput) for every count 1 .. the largest, the counts not
    measured interpolated."""
    known = sorted(measured)
    throughput = np.interp(np.arange(1, known[-1] + 1), known, [measured[k] for k in known])
    return tuple(float(t) for t in throughput)


def beside_others(measured: tuple[float, ...], others: float, cores: int) -> tuple[float, ...]:
    """``measured`` (the aggregate throughput of 1 .. K side-by-side processes, in
    single-process speeds) taken while ``others`` busy processes of others ran too, as the
    throughput of 1 .. K busy processes in all: what the simulator charges, where those
    others run beside its nodes again (``SharedCores(others=)``: k nodes as k + others busy
    processes). k measured processes ran among k + ``others``, each at the CPU efficiency
    of that many (relative to one measured process beside the others, which has a core to
    itself where ``others`` < ``cores``: efficiency 1), so n processes in all run at the
    efficiency measured at n - ``others``; at or under one, at one's. Reading the
    measurement at n instead counted the others twice: beside one busy process the probe
    read 1.78-1.91 for 2 processes (2.00 quiet) and the validation's 2-node rows then charged
    3 processes in all at its 4-process reading (2026-12-07).

    Parameters
    ----------
    measured : (K,) aggregate throughput, K >= 1 (``measured[0]`` is 1: a process alone).
    others : busy processes of others (>= 0, may be fractional) during the measurement.
    cores : the cores.

    Returns
    -------
    (K,) aggregate throughput with 1 .. K busy processes in all.
    """
    if others <= 0.0:
        return tuple(measured)
    counts = np.arange(1, len(measured) + 1, dtype=float)
    efficiency = np.asarray(measured) / np.minimum(counts, cores)
    ours = np.maximum(counts - others, 1.0)
    return tuple(float(v) for v in np.minimum(counts, cores) * np.interp(ours, counts, efficiency))


def throughput_counts(quick: bool, cores: int) -> list[int]:
    """The process counts measured: 1 .. 2 x ``cores`` and 4 x ``cores`` (quick: 1, cores,
    2 x cores, 4 x cores); the counts between are interpolated."""
    counts = {1, cores, 2 * cores} if quick else set(range(1, 2 * cores + 1))
    return sorted(counts | {4 * cores})


def process_costs(store_path: str, quick: bool, cores: int) -> tuple[float, ...]:
    """The aggregate throughput with k = 1 .. 4 x ``cores`` processes side by side, in
    single-process speeds (``throughput_counts``, the rest interpolated), measured
    in interleaved rounds by one set of warm processes (see the module docstring)."""
    counts = throughput_counts(quick, cores)
    processes = WarmProcesses(store_path, quick, counts[-1])
    try:
        rounds = measure_rounds(processes, counts, ROUNDS_QUICK if quick else ROUNDS)
    finally:
        processes.close()
    return interpolated(throughput_of(rounds, cores))


def measuring_render(prog: str, argv: list[str], tile_help: str):
    """(store, settings) of a measuring process's render from its command line (``STORE
    [--quick] [--tile]``): the calibration tile with ``--tile``, else twice its width and
    height (``calibrate.node_settings``)."""
    import argparse

    from vastray.scene.store import Store
    from vastray.sim.calibrate import calibration_settings, node_settings

    parser = argparse.ArgumentParser(prog=prog)
    parser.add_argument("store")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--tile", action="store_true", help=tile_help)
    args = parser.parse_args(argv)
    settings = calibration_settings(args.quick)
    return Store(args.store), settings if args.tile else node_settings(settings)


def main(argv: list[str]) -> int:
    from vastray.actors.job_options import JobOptions
    from vastray.actors.local import render_out_of_core
    from vastray.render.scene_config import SceneConfig

    # twice the calibration tile (about 1.4 s here): long enough for the processes' renders
    # to run side by side
    store, settings = measuring_render("python -m vastray.sim.warmup", argv,
                                       "render the calibration tile itself (a probe's "
                                       "shorter renders)")
    # one thread, as the simulated node and the validation's real ones (with all cores a
    # query of 8,192 rays or more would be split over both, and a render alone would not be
    # one core's work; this tile's queries are smaller, and its CPU and wall seconds alone
    # agree within 3 % either way)
    options = JobOptions(scheduler="image", threads=1)

    def render() -> float:
        start = time.process_time()
        render_out_of_core(store, SceneConfig(text=""), settings, options, progress=False)
        return time.process_time() - start

    render()  # first use: not timed
    print("ready", flush=True)
    for line in sys.stdin:  # "go": the processes told together render side by side
        if line.strip() == "go":
            print(json.dumps({"cpu_s": render()}), flush=True)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv[1:]))
    except InputError as exc:
        sys.exit(f"vastray.sim.warmup: {exc}")
