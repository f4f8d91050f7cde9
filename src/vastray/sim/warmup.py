"""The first-use cost of a fresh process, measured in one: ``python -m vastray.sim.warmup
STORE`` renders the calibration image out of core twice (the ``image`` schedule: scene set-up,
every domain loaded and its BVH built, the tile traced, the film filled) and prints the
seconds the first took beyond the second, as JSON. What every rendering node pays once:
compiled kernels loaded from numba's cache, Embree's device made, modules imported on first
use, first touches of memory."""

from __future__ import annotations

import json
import subprocess
import sys
import time

from vastray.scene.errors import InputError

#: Seconds the measuring process may take (it starts Python, imports, renders twice).
WARMUP_TIMEOUT_S = 300.0


def measure_warmup(store_path: str, quick: bool, repeats: int = 1) -> float:
    """Seconds of first-use cost in a fresh process (``python -m vastray.sim.warmup``), the
    median of ``repeats`` processes."""
    command = [sys.executable, "-m", "vastray.sim.warmup", str(store_path)]
    seconds = []
    for _ in range(repeats):
        try:
            done = subprocess.run(command + (["--quick"] if quick else []),
                                  capture_output=True, text=True, timeout=WARMUP_TIMEOUT_S,
                                  check=False)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"measuring a fresh process's first-use cost took over "
                               f"{WARMUP_TIMEOUT_S:.0f} s") from None
        if done.returncode != 0:
            raise RuntimeError(f"measuring a fresh process's first-use cost failed: "
                               f"{done.stderr.strip().splitlines()[-1:] or done.returncode}")
        seconds.append(float(json.loads(done.stdout)["warmup_s"]))
    return sorted(seconds)[len(seconds) // 2]


def main(argv: list[str]) -> int:
    from vastray.actors.job_options import JobOptions
    from vastray.actors.local import render_out_of_core
    from vastray.render.scene_config import SceneConfig
    from vastray.scene.store import Store
    from vastray.sim.calibrate import calibration_settings

    store = Store(argv[0])
    settings = calibration_settings("--quick" in argv)
    seconds = []
    for _ in range(2):
        start = time.perf_counter()
        render_out_of_core(store, SceneConfig(text=""), settings, JobOptions(scheduler="image"),
                           progress=False)
        seconds.append(time.perf_counter() - start)
    print(json.dumps({"warmup_s": max(0.0, seconds[0] - seconds[1])}))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv[1:]))
    except InputError as exc:
        sys.exit(f"vastray.sim.warmup: {exc}")
