"""Simulator commands: ``calibrate`` (measure the simulator's cost model on this machine and
write it as JSON, for ``vastray.sim``) and ``simulate`` (``commands_simulate``)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from vastray.scene.errors import InputError
from vastray.sim.costs import CostModel

CALIBRATE_EPILOG = """\
examples:
  vastray calibrate                         # the built-in scene -> costs.json (~1 min)
  vastray calibrate rm.store -o rm-costs.json
  vastray calibrate rm.store --quick        # smaller budgets (~20 s), rougher constants

what is measured, with the real components (nothing is mocked):
  loads       every domain of STORE loaded from the page cache (--cold-reads: from the
              disk, its pages dropped), the read of its files timed apart from its BVH build
  tracing     a 64x48 path-traced tile with the `image` schedule, every domain resident:
              each activation of a domain timed and fitted as a fixed cost (one for
              activations that shade, one for shadow-only ones) plus a cost per radiance
              query and per shadow query (shading apart, from the schedule's own clock);
              simulating on this machine charges each activation the CPU time its trace
              takes instead (trace_scale 1), and the same tile traced on a worker thread
              gives what a node runtime pays to hand each activation over (offload_s)
  the wire    ray batches of 0 to 100,000 rays between two processes over ZeroMQ in the
              wire format nodes use, fitted as a latency plus a cost per byte; then
              100-ray batches between two of the nodes' own management actors: the
              CPU a node pays per message it receives beyond that (receive_s)
  processes   1 to 2 x cores and 4 x cores warm processes rendering side by side,
              in interleaved rounds: the machine's throughput with k busy processes,
              from their CPU seconds (contention; the host's steal is not counted)
  a node      real `async`, `image` and `spec-insitu` renders of 16 x 12 pixels on 8
              node processes sharing the cores, against the simulator's predictions: what
              each node pays once (the least of the three: a fresh process's first use,
              warmup_s; the rest: each runtime's own)
The file also records the cores this process may use and what machine it ran on; run it
on an otherwise idle machine, as another process's load is measured too.
"""

#: What each constant is, for the table ``vastray calibrate`` prints.
COST_LABELS = {
    "trace_ray_s": "per radiance ray's closest-hit query",
    "shade_ray_s": "per radiance query shaded",
    "shadow_ray_s": "per shadow ray's occlusion query",
    "activation_s": "per activation tracing radiance rays",
    "shadow_activation_s": "per activation tracing shadow rays only",
    "camera_ray_s": "per camera ray",
    "load_byte_s": "per byte read from the store",
    "build_triangle_s": "per triangle of a BVH build",
    "read_fixed_s": "per domain read, besides its bytes",
    "build_fixed_s": "per BVH build, besides its triangles",
    "latency_s": "per message between processes",
    "byte_s": "per byte on the wire",
    "receive_s": "per message a node receives (its actors, beyond the wire)",
    "warmup_s": "once per fresh process (first use)",
    "node_setup_s": "once per node of a node runtime",
    "tile_setup_s": "once per sort-first node",
    "insitu_setup_s": "once per in-situ node",
    "page_fault_s": "per page of memory a fresh process touches first",
    "fresh_pages_per_path": "pages a fresh node touches first per path in flight",
    "decision_scale": "per CPU second a schedule decides (measured as it simulates)",
    "trace_scale": "per CPU second an activation traces (measured as it simulates)",
    "node_cpu_scale": "per CPU second a node's own code runs beyond those (measured so)",
    "load_scale": "per CPU second a domain's load takes (measured as it simulates)",
    "offload_s": "per activation a node runtime hands to a worker thread",
}


def register(sub: argparse._SubParsersAction) -> None:
    """Add the simulator's sub-commands (``calibrate``, ``simulate``)."""
    from vastray.commands_simulate import add_simulate

    fmt = argparse.RawDescriptionHelpFormatter
    _add_calibrate(sub, fmt)
    add_simulate(sub, fmt)


def _add_calibrate(sub: argparse._SubParsersAction, fmt) -> None:
    c = sub.add_parser(
        "calibrate", help="measure the simulator's costs on this machine (costs.json)",
        description="Measure what tracing, shading, loading domains and sending ray batches "
                    "cost on this machine, with vastray's own components, and write the "
                    "constants of the simulator's cost model as JSON.",
        epilog=CALIBRATE_EPILOG, formatter_class=fmt)
    c.add_argument("store", nargs="?", metavar="STORE",
                   help="domain store to measure with (default: the built-in scene, "
                        "generated on first use)")
    c.add_argument("-o", "--output", default="costs.json", metavar="FILE",
                   help="calibration file to write (default: costs.json)")
    c.add_argument("--quick", action="store_true",
                   help="smaller time budgets: about a third of the time, rougher constants")
    c.add_argument("--cold-reads", action="store_true",
                   help="time loads as reads of the disk (for `vastray render --cold-reads`)")
    c.add_argument("--quiet", action="store_true", help="no progress bar and no table")
    c.set_defaults(func=cmd_calibrate)


def cmd_calibrate(args) -> int:
    from vastray.sim.calibrate import CalibrationError, calibrate

    output = check_output_file(args.output)
    store, config, settings = _calibration_inputs(args)
    start = time.perf_counter()
    try:
        with _ProgressBar(enabled=not args.quiet and sys.stderr.isatty()) as bar:
            model = calibrate(store, quick=args.quick, progress=bar.update, config=config,
                              settings=settings, cold_reads=args.cold_reads)
    except CalibrationError as exc:
        print(f"vastray calibrate: error: {exc}", file=sys.stderr)
        return 1
    save_costs(model, output)
    if not args.quiet:
        print(costs_table(model, output, time.perf_counter() - start))
    return 0


def _calibration_inputs(args):
    """(store path, scene config, render settings): the built-in scene's when no STORE is
    given (its camera, lights and render defaults), else STORE's with a store's defaults."""
    from vastray.sim.calibrate import calibration_settings

    if args.store is not None:
        return Path(args.store), None, calibration_settings(args.quick)
    from vastray.default_scene import default_scene_config, default_store
    from vastray.request import BUILTIN_DEFAULTS

    settings = calibration_settings(args.quick, bounces=BUILTIN_DEFAULTS["bounces"],
                                    shadow_samples=BUILTIN_DEFAULTS["shadow_samples"])
    return default_store(quiet=args.quiet), default_scene_config(), settings


def check_output_file(name: str) -> Path:
    """The calibration file to write, checked before any measuring.

    Raises
    ------
    InputError
        Naming the file: it is a folder, its folder does not exist, or cannot be written.
    """
    path = Path(name)
    if path.is_dir():
        raise InputError(path, f"is a folder; give a file name such as {path / 'costs.json'}")
    folder = path.parent
    if not folder.is_dir():
        raise InputError(path, f"cannot be written: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(path, f"cannot be written: no permission to write in {folder}")
    return path


def save_costs(model: CostModel, path: Path) -> None:
    """``model.save(path)`` (written whole, then renamed); an ``InputError`` naming the file
    if it cannot be written."""
    try:
        model.save(path)
    except OSError as exc:
        raise InputError(path, f"cannot be written ({exc.strerror or exc})") from None


def costs_table(model: CostModel, path: Path, seconds: float) -> str:
    """The measured constants, one a line, and where they were written."""
    machine = model.machine
    where = ", ".join(str(x) for x in (machine.get("hostname"), machine.get("cpu"),
                                       f"{model.cores} cores") if x)
    lines = [f"calibrated in {seconds:.1f} s on {where}:"]
    for name, label in COST_LABELS.items():
        # a factor or a count of pages, not seconds
        unit = "x" if name.endswith("_scale") else "p" if name.startswith("fresh_pages") else "s"
        lines.append(f"  {name:<20} {getattr(model, name):10.3e} {unit}  {label}")
    lines.append(f"written to {path}")
    return "\n".join(lines)


class _ProgressBar:
    """A tqdm bar on stderr fed by ``calibrate``'s ``progress(fraction, text)``; nothing
    when not ``enabled``."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.bar = None

    def __enter__(self) -> _ProgressBar:
        if self.enabled:
            from vastray.scene.progressbar import Bar

            self.bar = Bar(total=100, desc="calibrate", leave=False,
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}{postfix}")
        return self

    def update(self, fraction: float, text: str) -> None:
        if self.bar is not None:
            self.bar.n = round(100 * fraction)
            self.bar.set_postfix_str(text)  # refreshes the bar

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()
