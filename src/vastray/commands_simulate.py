"""``vastray simulate``: a render on many virtual nodes in virtual time (``vastray.sim``), with
the costs ``vastray calibrate`` measured."""

from __future__ import annotations

import argparse
from pathlib import Path

SIMULATE_EPILOG = """\
examples:
  vastray calibrate -o costs.json                               # once per machine
  vastray simulate --nodes 1,16,256,1024 --scheduler async,domain,dynamic
  vastray simulate rm.store --nodes 64 --scheduler spec-insitu --costs costs.json -o sim.exr
  vastray simulate rm.store --nodes 4 --scheduler temporal,async --frames 4 --scene orbit.toml
  vastray simulate rm.store --nodes 4 --cores 2 --scheduler async   # 4 nodes on 2 cores
  vastray simulate rm.store --nodes 4 --cores calibrated          # ... on the calibrated machine's

Every virtual node runs the nodes' own code (the schedulers' policies of vastray.schedule,
the runtimes of vastray.actors, the tree reduce, the termination detection) over a simulated
network: rays are traced for real, so the image is the render's own and the traffic between
domains the true one, while time is the cost model's (per ray query and activation, per byte
loaded and triangle built, per message and byte sent: a tree reduction costs its messages,
and what a fresh node pays once). The simulated seconds are a node's busy time, as a real run's busy_max.
By default each node has a core of its own (a cluster); --cores N shares N cores between
them (node processes on one machine, as `vastray render --nodes` runs them), and --cores
calibrated the calibrated machine's cores.
"""


def add_simulate(sub: argparse._SubParsersAction, fmt) -> None:
    from vastray.request import (
        BUILTIN_DEFAULTS,
        STORE_DEFAULTS,
        _cache_size,
        _non_negative,
        positive_int,
    )
    from vastray.schedule.registry import SIMULATE_CHOICES as SIM_SCHEDULERS

    s = sub.add_parser(
        "simulate", help="simulate a render on many virtual nodes (speed-ups to 1024 nodes)",
        description="Simulate one render, or an animation, on P virtual nodes in virtual "
                    "time, for each scheduler and node count asked, and print the simulated "
                    "seconds and speed-ups.", epilog=SIMULATE_EPILOG, formatter_class=fmt)
    s.add_argument("store", nargs="?", help="STORE folder (default: the built-in scene)")
    s.add_argument("--nodes", type=_counts, default=[1, 2, 4, 8], metavar="P[,P...]",
                   help="virtual node counts (default: 1,2,4,8)")
    s.add_argument("--scheduler", type=_schedulers(SIM_SCHEDULERS), default=["async"],
                   metavar="S[,S...]",
                   help=f"schedulers, among {', '.join(SIM_SCHEDULERS)} (default: async)")
    s.add_argument("--costs", default="costs.json", metavar="FILE",
                   help="calibration file of `vastray calibrate` (default: costs.json)")
    s.add_argument("--cores", type=_cores, metavar="N|calibrated",
                   help="cores the nodes share: N, or 'calibrated' for the calibrated "
                        "machine's (to reproduce `vastray render --nodes` there; default: "
                        "one per node, a cluster)")
    s.add_argument("--warm", action="store_true",
                   help="nodes already started and warm: no first-use or set-up cost (a "
                        "long job's later frames, a running service)")
    s.add_argument("--scene", help="SCENE.toml with camera, lights and materials")
    s.add_argument("--integrator", choices=["ao", "pt"], default="pt",
                   help="ambient occlusion or path tracing (default: pt)")
    for name, kind in (("width", positive_int), ("height", positive_int), ("spp", positive_int),
                       ("bounces", _non_negative), ("shadow-samples", _non_negative)):
        key = name.replace("-", "_")
        s.add_argument(f"--{name}", type=kind,
                       help=f"as `vastray render` (default: {STORE_DEFAULTS[key]}; "
                            f"{BUILTIN_DEFAULTS[key]} for the built-in scene)")
    s.add_argument("--frames", type=positive_int, metavar="N",
                   help="an animation of N frames (the scene's camera keys or orbit)")
    s.add_argument("--cache", type=_cache_size, metavar="N|P%",
                   help="most domains in each node's memory (default: the scheduler's)")
    s.add_argument("--max-samples-in-flight", type=positive_int, metavar="N",
                   help="paths per tile (default: the nodes': 65536, or 4096 a node for a "
                        "domain-decomposition job on more than 16 nodes, at most 4194304)")
    s.add_argument("--max-pass-spp", type=positive_int, metavar="N",
                   help="render in sample-major passes of at most N spp, as `vastray render` "
                        "(default: one pass)")
    s.add_argument("-o", "--output", metavar="IMAGE",
                   help="also write the simulated render's image (.exr, .pfm, .hdr, .png)")
    s.add_argument("--report", metavar="FILE", help="write every run's figures as JSON")
    s.add_argument("--quiet", action="store_true", help="print nothing but errors")
    s.set_defaults(func=cmd_simulate)


def _cores(text: str) -> int | str:
    if text == "calibrated":
        return text
    try:
        cores = int(text)
    except ValueError:
        cores = 0
    if cores < 1:
        raise argparse.ArgumentTypeError(f"give a number of cores (at least 1) or "
                                         f"'calibrated', not {text!r}")
    return cores


def _counts(text: str) -> list[int]:
    try:
        counts = [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"node counts are integers, e.g. 1,8,64; got "
                                         f"{text!r}") from None
    if any(c < 1 for c in counts):
        raise argparse.ArgumentTypeError(f"node counts must be at least 1, got {text!r}")
    return counts


def _schedulers(known: tuple[str, ...]):
    def parse(text: str) -> list[str]:
        names = text.split(",")
        unknown = [n for n in names if n not in known]
        if unknown:
            raise argparse.ArgumentTypeError(f"unknown scheduler {unknown[0]!r}; the "
                                             f"simulator runs {', '.join(known)}")
        return names
    return parse


def cmd_simulate(args) -> int:
    from vastray.actors.job_options import JobOptions
    from vastray.render.driver import shading_inputs
    from vastray.render.imageio import check_image_path, write_image
    from vastray.render.integrators import RenderSettings
    from vastray.render.scene_config import load_scene_config
    from vastray.report import write_report
    from vastray.request import BUILTIN_DEFAULTS, STORE_DEFAULTS, resolve_cache
    from vastray.scene.store import Store
    from vastray.sim.cache import Domains
    from vastray.sim.costs import CostModel
    from vastray.sim.simulate import simulate

    costs = CostModel.load(args.costs)
    costs = costs.with_cores(costs.cores if args.cores == "calibrated" else args.cores)
    costs = costs.warm() if args.warm else costs
    if args.output:
        check_image_path(args.output)
    if args.store is None:
        from vastray.default_scene import default_scene_config, default_store

        store = Store(default_store(quiet=args.quiet))
        config, defaults = (load_scene_config(args.scene) if args.scene
                            else default_scene_config()), BUILTIN_DEFAULTS
    else:
        store, config, defaults = Store(Path(args.store)), load_scene_config(args.scene), \
            STORE_DEFAULTS
    settings = RenderSettings(**{k: getattr(args, k) if getattr(args, k) is not None else v
                                 for k, v in defaults.items()}, integrator=args.integrator)
    cache = resolve_cache(args.cache, len(store.domains))
    say = (lambda *a: None) if args.quiet else print
    say(f"simulating {store.path.name} ({len(store.domains)} domains), {settings.width}x"
        f"{settings.height}, {settings.spp} spp {settings.integrator}"
        f"{f', {args.frames} frames' if args.frames else ''}; costs of "
        f"{costs.machine.get('hostname', '?')} ({args.costs}), "
        f"{'one core per node' if costs.cores is None else f'{costs.cores} shared cores'}"
        f"{', warm nodes' if args.warm else ''}")
    domains = Domains(store, shading_inputs(store, config, settings.integrator)[1])
    runs, film = [], None
    try:
        for scheduler in args.scheduler:
            first = None
            for nodes in args.nodes:
                options = JobOptions(scheduler=scheduler, cache=cache,
                                     max_samples_in_flight=args.max_samples_in_flight)
                result = simulate(store, options, nodes, costs, settings, config,
                                  frames=args.frames, max_pass_spp=args.max_pass_spp,
                                  domains=domains)
                first = first or result
                runs.append(result.as_dict())
                film = result.film
                say(f"  {scheduler:11s} {nodes:5d} nodes: {result.seconds:9.4f} s simulated, "
                    f"speed-up {first.seconds / max(result.seconds, 1e-300):6.2f} vs "
                    f"{first.nodes} node(s); "
                    f"{result.messages:,} messages, {result.counters.get('loads', 0):,} loads "
                    f"({result.wall_s:.1f} s to simulate)")
    finally:
        domains.close()
    if args.output:
        write_image(args.output, film.image())
        say(f"wrote {args.output} (the last run's image)")
    if args.report:
        write_report(args.report, {"store": str(store.path), "settings": vars(settings),
                                   "frames": args.frames, "costs": costs.as_dict(),
                                   "runs": runs})
        say(f"wrote {args.report}")
    return 0
