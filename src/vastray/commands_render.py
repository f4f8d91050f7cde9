"""``vastray render`` and ``vastray compare``."""

from __future__ import annotations

import argparse
import functools
import logging
import math
import os
import signal
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.actors.results import recovery_lines
from vastray.animation import check_frame_outputs, run_animation
from vastray.checkpoint import Checkpointer, read_checkpoint, render_identity, saved_command
from vastray.checkpoint import default_path as default_checkpoint
from vastray.outputs import StagedOutputs
from vastray.preflight import (
    MemoryEstimate,
    RenderMemory,
    cache_within,
    check_limit_fits_machine,
    check_memory,
    check_output_paths,
    check_owned_fit,
    crossings_from_surface,
    domain_footprints,
    estimate_memory,
    gigabytes,
    parse_size,
    reference_paths_in_flight,
    speculative_copies,
)
from vastray.render.colormaps import Legend, colormap_lut, coloured_by_scalars, legend_for
from vastray.render.driver import FrameCache, RenderResult, render, store_camera
from vastray.render.imageio import image_error, read_image, write_image, write_png
from vastray.render.integrators import RenderSettings
from vastray.render.lights import shadow_rays
from vastray.render.progressive import DEFAULT_MAX_PASS_SPP, Progression, StopRules
from vastray.render.scene_camera import with_camera
from vastray.render.scene_config import SceneConfig, load_scene_config
from vastray.render_job import (
    DEFAULT_BATCH_SIZE,
    DEFAULT_EXPOSURE,
    DEFAULT_HEARTBEAT_TIMEOUT_S,
    DEFAULT_NODE_SAMPLES_IN_FLIGHT,
    DEFAULT_NODE_TIMEOUT_S,
    DEFAULT_SAMPLES_IN_FLIGHT,
    job_options,
    refuse_for_lights,
    refuse_for_scheduler,
    refuse_inapplicable,
)
from vastray.report import build_report, count_overflow, write_report
from vastray.scene.cpus import available_cpus
from vastray.scene.errors import InputError
from vastray.scene.extent import check_extent
from vastray.scene.store import Store
from vastray.schedule import portals
from vastray.transport.keys import (
    COORDINATOR_KEY,
    NODES_DIR,
    add_node_key,
    generate_keys,
    load_coordinator_keys,
    load_node_keys,
    node_bundle,
    write_bundle,
)

log = logging.getLogger(__name__)

#: Defaults for a user's store, and for the built-in scene (a first picture in a few seconds:
#: larger, smoother, one bounce and two shadow rays toward the sky).
STORE_DEFAULTS = {"width": 320, "height": 240, "spp": 4, "bounces": 3, "shadow_samples": 16}
BUILTIN_DEFAULTS = {"width": 640, "height": 480, "spp": 8, "bounces": 1, "shadow_samples": 2}

RENDER_EPILOG = """\
examples:
  vastray render -o default.exr --png default.png
      the built-in scene (a generated Richtmyer-Meshkov mixing layer, made on first use,
      coloured by how far the mixing carried the interface)
  vastray render bunny.store -o bunny.exr --integrator ao --spp 8 --ao-distance 0.02
  vastray render rm.store -o rm.exr --scene scene.toml --cache 4 --report rm.json
  vastray render rm.store -o rm.exr --cache 25% --scheduler spec-ooc --history-depth 2
  vastray render rm.store -o anim.exr --png anim.png --scene orbit.toml --frames 36 \\
      --report anim.json
      frames anim_0000.exr ... anim_0035.exr (orbit.toml: [camera.orbit] with
      degrees_per_frame = 10), a report per frame and the summary anim.json

The output format follows -o's extension: .exr holds RGB radiance plus depth.Z and
normal.X/Y/Z layers; .pfm and .hdr hold float RGB; .png is a clamped sRGB preview, as is --png.
Every output is checked before rendering and written only when the render succeeds.

Path tracing (pt) takes --bounces diffuse bounces after the first hit and does
next-event estimation to every light at each hit (so --bounces 0 is direct lighting only,
Mitsuba's max_depth = bounces + 2). Images are identical whatever --cache and --batch-size.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render", help="render a store (or the built-in scene) to an image (.exr, .pfm, .hdr or "
                       ".png), and on request a PNG preview and a JSON report",
        description="Render a domain store with ambient occlusion or path tracing.",
        epilog=RENDER_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_render_arguments(p)
    p.set_defaults(func=run_render)

    launch = sub.add_parser(
        "launch", help="render with nodes started on SSH hosts",
        description=LAUNCH_DESCRIPTION, epilog=LAUNCH_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    launch.add_argument("--hosts", required=True, metavar="HOSTFILE",
                        help="one node per line: HOST [python=PATH] [slots=N]")
    launch.add_argument("--advertise", help="address the hosts reach this machine at "
                                            "(default: its fully qualified host name)")
    launch.add_argument("--port", type=_positive, help="coordinator port (default: a free one)")
    launch.add_argument("--ssh", default="ssh -o BatchMode=yes -tt",
                        help="command that runs a command on a host (default: %(default)s)")
    launch.add_argument("--node-keys", metavar="PATH",
                        help="where each host holds its own bundle, a copy of "
                             "KEYS/bundles/HOST (default: KEYS/bundles/HOST itself, on a "
                             "disk the hosts share)")
    launch.add_argument("--logs", default="vastray-logs",
                        help="folder for the node logs, created if absent (default: "
                             "%(default)s)")
    add_render_arguments(launch)
    launch.set_defaults(func=run_launch)
    _register_keys_and_compare(sub)


def add_render_arguments(p: argparse.ArgumentParser) -> None:
    """The options shared by ``render`` and ``launch``."""
    p.add_argument("store", nargs="?", help="STORE folder (default: the built-in scene)")
    p.add_argument("-o", "--output", required=True,
                   help="output image; the extension picks the format: .exr (float RGB plus "
                        "depth and normal layers), .pfm, .hdr or .png. Like --png and "
                        "--report, an existing file is replaced (the last line says so)")
    p.add_argument("--png", help="also write a tone-mapped PNG preview")
    p.add_argument("--scene", help="SCENE.toml with camera, lights and materials")
    p.add_argument("--integrator", choices=["ao", "pt"], default="pt",
                   help="ambient occlusion or path tracing (default: pt)")
    p.add_argument("--spp", type=_positive,
                   help=f"samples per pixel (default: {STORE_DEFAULTS['spp']}; "
                        f"{BUILTIN_DEFAULTS['spp']} for the built-in scene)")
    p.add_argument("--bounces", type=_non_negative,
                   help=f"diffuse bounces for pt (default: {STORE_DEFAULTS['bounces']}, as in "
                        f"the SpRay paper; {BUILTIN_DEFAULTS['bounces']} for the built-in scene)")
    p.add_argument("--shadow-samples", type=_non_negative,
                   help="shadow rays per hit toward each area/ambient light, and AO rays per "
                        f"hit (default: {STORE_DEFAULTS['shadow_samples']}; "
                        f"{BUILTIN_DEFAULTS['shadow_samples']} for the built-in scene)")
    p.add_argument("--ao-distance", type=_positive_float,
                   help="AO ray length (default: a tenth of the scene diagonal)")
    p.add_argument("--width", type=_positive,
                   help=f"image width (default: {STORE_DEFAULTS['width']}; "
                        f"{BUILTIN_DEFAULTS['width']} for the built-in scene)")
    p.add_argument("--height", type=_positive,
                   help=f"image height (default: {STORE_DEFAULTS['height']}; "
                        f"{BUILTIN_DEFAULTS['height']} for the built-in scene)")
    p.add_argument("--seed", type=_non_negative, default=0, help="random seed (default: 0)")
    p.add_argument("--cache", type=_cache_size, metavar="N|P%",
                   help="most domains in memory at once, as a count or a percentage of the "
                        "domains (default: all)")
    p.add_argument("--scheduler",
                   choices=["auto", "reference", "image", "spec-ooc", "domain", "async",
                            "dynamic", "spec-insitu", "temporal"],
                   default="auto",
                   help="how rays meet domains: 'reference' traces each wavefront through all "
                        "domains it enters; 'image' queues rays per domain and processes the "
                        "fullest (SpRay's baseline); 'spec-ooc' is SpRay's speculative "
                        "out-of-core schedule. With --nodes also 'domain' (static domain "
                        "ownership, synchronous rounds), 'async' (owned domains, rays move "
                        "without global rounds), 'dynamic' (Navratil's ray-weighted rounds "
                        "re-assigning domains) and 'spec-insitu' (SpRay in situ: z-order "
                        "ownership, speculation, t-buffer MIN / o-buffer OR all-reduce) and "
                        "'temporal' (async with each frame's domain groups and screen tiles "
                        "planned from the last frame's ray statistics, and cost-based "
                        "preloading: Xu et al. 2022). All give the same image. 'auto' (default): "
                        "reference when every domain fits in the cache, else spec-ooc")
    p.add_argument("--memory-limit", type=_size, metavar="SIZE",
                   help="most memory each process (each node) may use, e.g. 8G or 700M (K, M, G, "
                        "T: KiB, MiB, GiB, TiB): bounds its "
                        "domain cache after the rest of the process (interpreter and "
                        "libraries, film, paths in flight, and a 75 MB margin for the "
                        "libraries' measured spread); the report's peak_rss_bytes is the "
                        "measured peak; a render that cannot fit is "
                        "refused before it starts (default: a render is refused only when it "
                        "needs more than 85%% of the available memory)")
    p.add_argument("--max-samples-in-flight", type=_positive, metavar="N",
                   help="out-of-core (image, spec-ooc) and every --nodes scheduler: paths "
                        "traced at once; bounds the rays held in memory (default: 262144; "
                        "with --nodes, 65536 per node)")
    p.add_argument("--history-depth", type=_non_negative, metavar="H",
                   help="spec-ooc: bounces speculated before hits are resolved "
                        "(default: --bounces, the most aggressive)")
    p.add_argument("--nodes", type=_positive, metavar="N",
                   help="render with N node processes on this machine, talking ZeroMQ over "
                        "loopback: image and spec-ooc split the image into tiles (sort-first); "
                        "domain, async, dynamic, spec-insitu and temporal split the domains "
                        "(see --scheduler)")
    p.add_argument("--node-timeout", type=_positive_float, metavar="S",
                   help="with --nodes: fail when a node is silent this long (default: 120)")
    p.add_argument("--log-dir", metavar="DIR",
                   help="with --nodes (started here): keep each node's log in DIR "
                        "(nodeR.log: its failures and the messages and connections it "
                        "refused); default: beside --report as REPORT.nodes, else removed "
                        "when the render ends")
    p.add_argument("--heartbeat-timeout", type=_positive_float, metavar="S",
                   help="with --nodes: a node silent this long mid-frame is lost (stalled); "
                        "it is survived by rendering the frame again on the others (with "
                        "--listen, once they have joined again) (default: 10)")
    p.add_argument("--listen", metavar="HOST:PORT",
                   help="with --nodes N: wait for N nodes started elsewhere (`vastray node "
                        "--coordinator tcp://HOST:PORT`, docker compose, SSH) instead of "
                        "starting them here")
    p.add_argument("--rendezvous", metavar="FILE",
                   help="with --listen: write this coordinator's address into FILE on a file "
                        "system the nodes share, for `vastray node --rendezvous FILE` under "
                        "srun or mpirun (`vastray node --help` shows a Slurm job)")
    p.add_argument("--keys", metavar="DIR",
                   help="with --listen: the key folder from `vastray keys` (ZeroMQ CURVE: "
                        "encrypted; a node joins only with its own key on DIR/public's "
                        "allow-list); needed to listen beyond loopback. Without it only nodes "
                        "of your user on this machine may join")
    p.add_argument("--no-preload", action="store_true",
                   help="do not load the next domain in the background (every scheduler with "
                        "a cache; the 'no preloading' rows of the benchmarks)")
    p.add_argument("--assignment", choices=["sequential", "spatial", "paper", "affinity"],
                   help="async/temporal: which node owns which domain: round robin "
                        "(sequential; async's default), contiguous z-order runs (spatial), "
                        "the temporal-coherence paper's Algorithm 1 from the last frame's ray "
                        "transmissions (paper), or Algorithm 1 where a domain a node holds "
                        "stays there unless moving it saves more than its load (affinity; "
                        "temporal's default). Frame 0 uses spatial for both")
    p.add_argument("--priority", choices=["queue", "spray", "queue+act", "cost-benefit",
                                          "cost-rate", "queue+resident"],
                   help="temporal: how a node picks the next domain and what it preloads: "
                        "most queued rays (queue), SpRay's traversal score, queued plus "
                        "expected rays from the active domain (queue+act), the paper's "
                        "cost-benefit Eq. 1 as written (predicted work minus load time), "
                        "cost-rate (default: Eq. 1's predicted work per second of loading, so "
                        "cached domains go first), or queue+resident (most queued rays, cached "
                        "domains first: the queue baseline made cache-aware)")
    p.add_argument("--simplified", nargs="?", const="portal", metavar="POLICY",
                   choices=["portal", "depth>0", "depth>1", "depth>2", "none"],
                   help="async/temporal: trace some rays on the store's simplified model "
                        "(`vastray simplify STORE --ratio 0.01`) held by every node, never "
                        "sending them between nodes: 'portal' (default) sends depth-1 rays "
                        "whose virtual portal predicts little light, and every deeper ray; "
                        "'depth>K' every ray deeper than K; 'none' nothing. Lossy: compare "
                        "with --reference")
    p.add_argument("--portal-interval", type=_positive, metavar="N",
                   help="--simplified portal: record the portals every N frames (default 10)")
    p.add_argument("--portal-memory", type=_positive, metavar="N",
                   help="--simplified portal: frames between recording frames record too, "
                        "from the depth-1 rays they trace fine, and a cell no frame has "
                        "recorded for N frames is forgotten (default: off, the paper's: only "
                        "every --portal-interval-th frame records). Fills the portals of "
                        "small frames, whose few paths leave most cells unrecorded")
    p.add_argument("--portal-resolution", type=_portal_resolution, metavar="R",
                   help="--simplified portal: cells per portal edge, R x R x 8 directions on "
                        "each domain face (default 32, the paper's; its Table 4 sweeps "
                        "8-128). Coarser portals fill with fewer paths: at small images most "
                        "crossings of a 32 x 32 portal land in cells no path has recorded, "
                        "which are traced fine")
    p.add_argument("--portal-threshold", type=float, metavar="L",
                   help="--simplified portal: predicted radiance at or below which a depth-1 "
                        "ray goes to the simplified model (default 0.5)")
    p.add_argument("--portal-accuracy", action="store_true",
                   help="--simplified portal: an instrumented run for evaluation, not for "
                        "timing: every frame is traced as a recording frame (every depth-1 "
                        "ray on the full model) and each depth-1 portal crossing is "
                        "classified with the portals a timed run would predict it with; each "
                        "frame's report gets acc (the paper's prediction accuracy), "
                        "acc_simplified_share, acc_unrecorded_share and replay_false_low")
    p.add_argument("--load-bandwidth", type=_bandwidths, metavar="MB/s[,MB/s...]",
                   help="emulate network storage, for every scheduler: a domain load takes at "
                        "least its size over this bandwidth (per process; with --nodes a list "
                        "is cycled over the ranks); an emulation by waiting after the real "
                        "read, for benchmarks. The report gives bytes_loaded and "
                        "load_throttle_s, the time spent waiting")
    p.add_argument("--cold-reads", action="store_true",
                   help="out of core (image, spec-ooc and the node schedulers with a cache): "
                        "drop each domain's files from the page cache as they are read "
                        "(posix_fadvise DONTNEED), so every reload after an eviction is a real "
                        "disk read; the report gives bytes_loaded, load_s and load_wait_s, the "
                        "time the renderer waited on loads")
    p.add_argument("--eviction", choices=["lru", "demand"], default="lru",
                   help="image and spec-ooc: which domain a load evicts: the least recently "
                        "used (lru, default) or the one the schedule will need last by its "
                        "own order (demand: the emptiest queue for image, the latest in the "
                        "round for spec-ooc; an approximation of Belady's rule); the report's "
                        "belady_loads is the fewest loads the run's own domain order allows")
    p.add_argument("--batch-size", type=_positive,
                   help="in-core reference render: paths traced together (default: 65536; cut "
                        "finer when a frame has fewer than two batches per render worker)")
    p.add_argument("--threads", type=_positive,
                   help="threads per process (default: the cores it may use, its CPU affinity "
                        "and cgroup CPU quota (docker --cpus); with --nodes N on this machine, "
                        "those / N per node; with --listen, each node's own). In "
                        "core, one render worker per thread traces batches side by side; out of "
                        "core, each Embree query splits its rays over the threads")
    p.add_argument("--report", help="write a JSON report (timings, counts, error)")
    p.add_argument("--reference",
                   help="reference image (.exr/.pfm/.npy) to report MSE, PSNR and relative MSE "
                        "against; with --frames, a pattern such as ref_{frame:04d}.exr or a "
                        "plain name ref.exr meaning ref_0000.exr, ref_0001.exr ...")
    p.add_argument("--frames", type=_positive, metavar="N",
                   help="render an animation of N frames (moved by the scene's "
                        "[[camera.key]], [camera.orbit], [[light.key]] or light move); -o "
                        "a.exr writes "
                        "a_0000.exr, a_0001.exr ..., as do --png and --report, and the "
                        "--report path gets a summary of every frame. Frame f uses the seed "
                        "hash(--seed, f) (default: one image, no numbering, the seed as given)")
    p.add_argument("--first-frame", type=_non_negative, metavar="F",
                   help="the first frame's number (default: 0); without --frames, "
                        "renders that one frame (numbered outputs, its own seed)")
    p.add_argument("--exposure", type=_positive_float,
                   help="PNG exposure multiplier, for --png or a .png -o (default: 1)")
    p.add_argument("--colormap", metavar="NAME",
                   help="matplotlib colour map for a store coloured by its scalar field, e.g. "
                        "viridis, plasma, coolwarm, turbo (needs matplotlib: pip install "
                        "'vastray[plot]'; default: a built-in viridis)")
    p.add_argument("--color-range", type=_finite_float, nargs=2, metavar=("LO", "HI"),
                   help="map scalars LO..HI to the colour map's ends, whatever the store's "
                        "range (ParaView's custom range), so renders of different data, every "
                        "frame and every node share one scale (default: the store's range)")
    p.add_argument("--legend", action=argparse.BooleanOptionalAction, default=None,
                   help="draw a colour bar (the scalar's name and range) along the bottom of "
                        "the PNG of a store coloured by scalars (default: with --colormap)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    passes = p.add_argument_group(
        "progressive passes, stopping rules and checkpoints",
        "Every render runs in sample-major passes: pass k adds samples to every pixel "
        "(1, 1, 2, 4, 8, ... per pixel, then at most --max-pass-spp), so the image after any "
        "pass is the whole image at fewer samples, the same whatever the scheduler or node "
        "count. The report's 'passes' gives each pass's time, spp, error against "
        "--reference (MSE, relMSE, PSNR) and the film's own variance estimate and 95% "
        "confidence interval; `vastray plot` draws them. --spp is the upper bound.")
    passes.add_argument("--time-limit", type=_positive_float, metavar="SECONDS",
                        help="stop before a pass that would end after SECONDS of rendering "
                             "(predicted from the pass before; the first pass always runs)")
    passes.add_argument("--target-error", type=_positive_float, metavar="E",
                        help="stop after the pass whose relative MSE is at most E: against "
                             "--reference, or without one as the film estimates it from its "
                             "own variance (from 2 spp on), e.g. 0.01")
    passes.add_argument("--max-pass-spp", type=_positive, metavar="N",
                        help=f"most samples per pixel one pass adds (default: "
                             f"{DEFAULT_MAX_PASS_SPP}): smaller gives more points and "
                             "checkpoints, larger less overhead per pass")
    passes.add_argument("--checkpoint-every", type=_positive_float, metavar="SECONDS",
                        help="every SECONDS (at the end of a pass), write the image so far to "
                             "-o (and --png) and the film to --checkpoint. SIGUSR1 writes one "
                             "at once; Ctrl-C writes one before exiting. A run that completes "
                             "removes the checkpoint it wrote")
    passes.add_argument("--checkpoint", metavar="FILE",
                        help="where checkpoints go (default: -o's name + .checkpoint.npz)")
    passes.add_argument("--resume", metavar="CHECKPOINT",
                        help="go on from a checkpoint: `vastray render --resume FILE` alone "
                             "runs the command that wrote it again (kept in it), with what "
                             "else you type on top (--spp may be larger; any --nodes and "
                             "lossless scheduler); given a STORE, it takes the options typed "
                             "now. The image is the one an uninterrupted run gives")


def _register_keys_and_compare(sub: argparse._SubParsersAction) -> None:
    k = sub.add_parser(
        "keys", help="make the coordinator's and the nodes' key pairs (ZeroMQ CURVE) for --keys",
        description="Write the coordinator's key pair into a folder (once), and a key pair "
                    "for each node named with --node, whose public key goes on the folder's "
                    "allow-list (DIR/public), and each node's bundle, DIR/bundles/NAME: its "
                    "own key pair and the coordinator's public key, nothing else. DIR stays "
                    "with the coordinator; host NAME is given only DIR/bundles/NAME, so that "
                    "once `rm DIR/public/NAME.key` shuts it out, no key it holds lets it in.",
        epilog="examples:\n  vastray keys -o cluster-keys --node gpu01 --node gpu02\n"
               "  scp -r cluster-keys/bundles/gpu01 gpu01:vastray-keys   # gpu02's to gpu02\n"
               "  vastray render s.store -o o.exr --nodes 2 --listen 0.0.0.0:5555 "
               "--keys cluster-keys\n"
               "  vastray node --coordinator tcp://head:5555 --bind 0.0.0.0 "
               "--keys vastray-keys   # on gpu01\n"
               "  rm cluster-keys/public/gpu02.key   # gpu02 may join no more",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    k.add_argument("-o", "--output", required=True, help="folder to write the keys into")
    k.add_argument("--node", action="append", metavar="NAME", default=[],
                   help="give node NAME its own key pair and bundle and allow it in "
                        "(repeatable)")
    replace = k.add_mutually_exclusive_group()
    replace.add_argument("--force", action="store_true",
                         help="replace key pairs already in the folder (nodes holding the old "
                              "ones can no longer join)")
    replace.add_argument("--keep-existing", action="store_true",
                         help="keep key pairs already in the folder and succeed (for scripts "
                              "and docker compose that run this on every start)")
    k.set_defaults(func=run_keys)

    c = sub.add_parser(
        "compare", help="print MSE, PSNR and max difference of two images",
        description="Compare two images (.exr or .npy, same size).",
        epilog="example:\n  vastray compare render.exr reference.exr",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    c.add_argument("image")
    c.add_argument("reference")
    c.set_defaults(func=run_compare)


def run_keys(args: argparse.Namespace) -> int:
    key_file = Path(args.output) / COORDINATOR_KEY
    if key_file.exists() and (args.keep_existing or (args.node and not args.force)):
        load_coordinator_keys(args.output)  # refuses a malformed one
        print(key_file)
    else:
        print(generate_keys(args.output, args.force))
    for name in args.node:
        node_file = Path(args.output) / NODES_DIR / f"{name}.key"
        if args.keep_existing and node_file.exists():
            load_node_keys(args.output, name)
            print(node_file)
        else:
            print(add_node_key(args.output, name, args.force))
    # every node's bundle, so that all follow a replaced coordinator key
    for node_file in sorted((Path(args.output) / NODES_DIR).glob("*.key")):
        bundle = write_bundle(args.output, node_file.stem)
        if node_file.stem in args.node:
            print(bundle)
    return 0


def _size(text: str) -> int:
    try:
        return parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _positive(text: str) -> int:
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _portal_resolution(text: str) -> int:
    value = _positive(text)
    if value > portals.MAX_RESOLUTION:
        raise argparse.ArgumentTypeError(f"at most {portals.MAX_RESOLUTION} (the paper's "
                                         f"largest), got {value}")
    return value


def _cache_size(text: str) -> int | str:
    """``N`` domains or ``P%`` of the domains (resolved once the store is open)."""
    if text.endswith("%"):
        value = float(text[:-1])
        if not 0 < value <= 100:
            raise argparse.ArgumentTypeError(f"percentage must be in (0, 100], got {text}")
        return text
    return _positive(text)


def resolve_cache(cache: int | str | None, n_domains: int) -> int | None:
    """The cache size in domains: ``P%`` of ``n_domains`` rounded up (at least 1)."""
    if isinstance(cache, str):
        return max(1, math.ceil(float(cache[:-1]) / 100.0 * n_domains))
    return cache


def _bandwidths(text: str) -> float | list[float]:
    """``MB/s`` or a comma-separated list of them (one per rank, cycled)."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MB/s numbers like 200 or 200,100; got "
                                         f"{text!r}") from None
    if not all(0 < v < float("inf") for v in values):
        raise argparse.ArgumentTypeError(f"bandwidths must be positive, got {text!r}")
    return values[0] if len(values) == 1 else values


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None


def _non_negative(text: str) -> int:
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {value}")
    return value


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
    return value


LAUNCH_DESCRIPTION = """\
Render on a cluster of SSH hosts: starts one `vastray node` per HOSTFILE entry with plain ssh,
coordinates them from here, collects their logs, and closes every session when the render
ends, fails or is interrupted. The STORE must be at the same path on every host; each node
uses its host's own key bundle (--node-keys); traffic is CURVE-encrypted."""

LAUNCH_EPILOG = """\
example (one key per host, named as in hosts.txt; keys/ stays here, each host gets its bundle):
  vastray keys -o keys --node gpu01 --node gpu02
  scp -r keys/bundles/gpu01 gpu01:vastray-keys   # and gpu02's to gpu02
  vastray launch --hosts hosts.txt /shared/rm.store -o rm.exr --keys keys \\
      --node-keys vastray-keys --scheduler spec-ooc --cache 25%
"""


def run_launch(args: argparse.Namespace) -> int:
    from vastray.actors.launch import (
        host_key_name,
        read_hostfile,
        start_nodes,
        stop_nodes,
        this_host,
    )

    if not args.keys:
        raise InputError(None, "launch needs --keys DIR (make them with `vastray keys -o DIR "
                               "--node HOST ...`, one per host)")
    for flag, given in (("--nodes", args.nodes), ("--listen", args.listen),
                        ("--rendezvous", args.rendezvous)):
        if given:  # launch sets them itself
            raise InputError(None, f"launch starts one node per HOSTFILE line (slots=N for "
                                   f"more) and listens on --port; {flag} is for `vastray "
                                   "render`")
    hosts = read_hostfile(args.hosts)
    bundles = {}
    for host in {h.name for h in hosts}:  # each host's own key, before any ssh session
        load_node_keys(args.keys, host_key_name(host))
        bundles[host] = args.node_keys or str(
            node_bundle(Path(args.keys).resolve(), host_key_name(host)))
    port = args.port or _free_port()
    coordinator = f"tcp://{args.advertise or this_host()}:{port}"
    started = start_nodes(hosts, coordinator, bundles, Path(args.logs),
                          ssh=args.ssh, timeout=args.node_timeout or DEFAULT_NODE_TIMEOUT_S)
    if not args.quiet:
        print(f"{len(hosts)} node(s) started; their logs are in {args.logs}", file=sys.stderr)
    args.nodes, args.listen = len(hosts), f"0.0.0.0:{port}"
    try:
        return run_render(args, launched=started)
    finally:
        stop_nodes(started)


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("", 0))
        return probe.getsockname()[1]


def resolve_defaults(args: argparse.Namespace) -> None:
    """Fill the options left unset with the defaults of the built-in scene or of a store (and
    the defaults of the options ``refuse_inapplicable`` checks for presence)."""
    defaults = BUILTIN_DEFAULTS if args.store is None else STORE_DEFAULTS
    defaults = dict(defaults, exposure=DEFAULT_EXPOSURE,
                    node_timeout=DEFAULT_NODE_TIMEOUT_S,
                    heartbeat_timeout=DEFAULT_HEARTBEAT_TIMEOUT_S)
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)


@dataclass
class RenderPlan:
    """A render checked and ready to run, as ``vastray render`` and ``vastray.render`` (the
    Python API) both prepare it with ``plan_render``.

    Attributes
    ----------
    store_path : the store's folder (the built-in scene's, without a store).
    store : the opened store.
    config : camera, lights and materials.
    settings : image size, integrator and sampling (defaults filled in).
    scheduler : as resolved from ``auto``.
    options : the job's options, as the schedulers receive them.
    report_options : the run's switches, as its report records them (``run_options``).
    reference : (H, W, 3) image to measure the error against, or None.
    render_one : ``render_one(config, settings) -> RenderResult`` (``_renderer``).
    legend : the colour bar PNGs get, or None (``png_legend``).
    memory : the peak memory the preflight expects (``preflight.RenderMemory``).
    """

    store_path: Path
    store: Store
    config: SceneConfig
    settings: RenderSettings
    scheduler: str
    options: JobOptions
    report_options: dict
    reference: np.ndarray | None
    render_one: Callable[..., RenderResult]
    legend: Legend | None = None
    rules: StopRules | None = None
    memory: RenderMemory | None = None

    def progression(self, reference: np.ndarray | None = None,
                    resumed=None) -> Progression:
        """A fresh ``Progression`` of one image with the plan's stopping rules, measured
        against ``reference`` (default: the plan's)."""
        return Progression(self.settings.width, self.settings.height,
                           self.rules or StopRules(self.settings.spp),
                           self.reference if reference is None else reference,
                           resumed=resumed)


def check_and_default(args: argparse.Namespace) -> bool:
    """Refuse the options given where they change nothing, then fill in the defaults.
    Returns whether ``--shadow-samples`` was given (``plan_render`` needs to know)."""
    refuse_inapplicable(args)  # before the defaults fill in what was not given
    shadow_samples_given = args.shadow_samples is not None
    resolve_defaults(args)
    return shadow_samples_given


def plan_render(args: argparse.Namespace, shadow_samples_given: bool, *,
                animating: bool = False, launched: dict | None = None,
                store: Store | None = None, camera: dict | None = None) -> RenderPlan:
    """Open the store and scene, refuse what cannot work, and pick the scheduler and the
    job's options: everything before the first ray, for ``args`` as ``check_and_default``
    left them.

    Parameters
    ----------
    animating : an animation checks the camera (and reference) of each of its frames.
    launched : node processes started elsewhere (``vastray launch``).
    store : ``args.store`` already opened.
    camera : ``[camera]`` keys replacing the scene's camera (``scene_config.with_camera``).

    Raises
    ------
    InputError
        Naming the file or option and the problem.
    """
    if args.store is None:
        from vastray.default_scene import default_scene_config, default_store

        store_path = default_store(quiet=args.quiet)
        config = load_scene_config(args.scene) if args.scene else default_scene_config()
    else:
        store_path = Path(args.store)
        config = load_scene_config(args.scene)
    store = Store(store_path) if store is None else store
    check_extent(store.bounds, store.path, "partition it again")
    if camera is not None:
        config = with_camera(config, camera)
    config.check_objects(store.objects)
    legend = png_legend(args, store)
    refuse_for_lights(args, shadow_samples_given, config.resolve_lights())
    if not animating:  # an animation checks the camera of each of its frames
        config.resolve_camera(*store.world_bounds, args.width, args.height)
    reference = None
    if isinstance(args.reference, np.ndarray):
        reference = args.reference
    elif args.reference and not animating:
        reference = read_image(args.reference)
    settings = RenderSettings(
        width=args.width, height=args.height, spp=args.spp, integrator=args.integrator,
        bounces=args.bounces, shadow_samples=args.shadow_samples, ao_distance=args.ao_distance,
        seed=args.seed, batch_size=args.batch_size or DEFAULT_BATCH_SIZE,
        colormap=args.colormap,
        color_min=args.color_range[0] if args.color_range else None,
        color_max=args.color_range[1] if args.color_range else None,
    )
    if reference is not None and reference.shape != (args.height, args.width, 3):
        where = args.reference if isinstance(args.reference, str) else "reference"
        raise InputError(where, f"reference is {reference.shape[1]}x{reference.shape[0]}"
                                f", the render is {args.width}x{args.height}")
    cache = resolve_cache(args.cache, len(store.domains))
    scheduler = args.scheduler
    cache, memory = _check_render_memory(args, config,
                                         "reference" if scheduler == "auto" else scheduler,
                                         store, cache)
    if scheduler == "auto":
        scheduler = "reference" if cache is None or cache >= len(store.domains) else "spec-ooc"
    if args.rendezvous and not args.listen:
        raise InputError(None, "--rendezvous FILE needs --listen HOST:PORT (the nodes it "
                               "guides are started elsewhere)")
    if args.keys and not args.listen:
        raise InputError(None, "--keys is for nodes started elsewhere (--listen HOST:PORT); "
                               "the nodes --nodes starts here join with a secret handed to "
                               "them")
    if args.keys:
        load_coordinator_keys(args.keys)  # a missing or malformed key fails before the render
    if args.log_dir and args.listen:
        raise InputError(None, "--log-dir keeps the logs of nodes started here; nodes started "
                               "elsewhere (--listen) keep their own (`vastray launch --logs`)")
    if scheduler in ("domain", "async", "dynamic", "spec-insitu", "temporal") and not args.nodes:
        raise InputError(None, f"--scheduler {scheduler} distributes domains over nodes; "
                               "give --nodes N")
    if args.nodes:
        scheduler = "image" if scheduler == "reference" else scheduler
        cores = available_cpus()
        if not args.listen and args.nodes > cores:
            log.warning("--nodes %d on %d core(s): the nodes share them, so more than %d "
                        "nodes render no faster here", args.nodes, cores, cores)
    refuse_for_scheduler(args, scheduler)
    refuse_for_passes(args, animating)
    options = job_options(args, scheduler, cache)
    rules = StopRules(args.spp, args.time_limit, args.target_error,
                      args.max_pass_spp or DEFAULT_MAX_PASS_SPP)
    return RenderPlan(store_path, store, config, settings, scheduler, options,
                      run_options(args, options), reference,
                      _renderer(args, store, store_path, options, launched), legend, rules,
                      memory)


def refuse_for_passes(args: argparse.Namespace, animating: bool) -> None:
    """Refuse checkpoint options where they cannot work.

    Raises
    ------
    InputError
        Naming the option and what to do instead.
    """
    for dest in ("checkpoint_every", "checkpoint", "resume"):
        if getattr(args, dest, None) is not None and animating:
            raise InputError(None, f"--{dest.replace('_', '-')} is for one image; an animation goes on "
                                   "from a frame with --first-frame F")
    if args.resume is not None and args.simplified not in (None, "none"):
        raise InputError(args.resume, "--resume is for lossless renders: --simplified keeps "
                                      "a radiance cache that is not in the checkpoint")
    if (getattr(args, "target_error", None) is not None and not args.reference
            and args.simplified not in (None, "none")):
        raise InputError(None, "--target-error without --reference is for lossless renders: "
                               "--simplified is biased, and the film's error estimate sees "
                               "its noise, not its bias (give --reference IMAGE)")
    if args.checkpoint is not None and args.checkpoint_every is None:
        log.info("--checkpoint without --checkpoint-every: written on SIGUSR1 and Ctrl-C")


def finish_render(plan: RenderPlan, result: RenderResult, where: str | os.PathLike,
                  reference_name: str | None) -> tuple[np.ndarray, dict | None, dict]:
    """A finished render's image ((H, W, 3) as the film holds it), its error against the
    plan's reference (or None) and its report (the dict ``--report`` writes); non-finite
    pixels are counted (and said on stderr, naming ``where``)."""
    image = result.film.image()
    count_overflow(image, result.counters, where)
    error = image_error(image, plan.reference) if plan.reference is not None else None
    report = build_report(
        store=str(plan.store_path), settings=asdict(plan.settings), seconds=result.seconds,
        counters=result.counters, error=error, reference=reference_name,
        scheduler=plan.scheduler, options=plan.report_options, progress=result.progress,
    )
    return image, error, report


def run_render(args: argparse.Namespace, launched: dict | None = None) -> int:
    shadow_samples_given = check_and_default(args)
    animating = args.frames is not None or args.first_frame is not None
    if animating:
        first = args.first_frame or 0
        frame_outputs = check_frame_outputs(args.output, args.png, args.report,
                                            list(range(first, first + (args.frames or 1))))
    else:
        outputs = check_output_paths(args.output, args.png, args.report)
    plan = plan_render(args, shadow_samples_given, animating=animating, launched=launched)
    if animating:
        return run_animation(args, store_path=str(plan.store_path), config=plan.config,
                             settings=plan.settings, bounds=plan.store.world_bounds,
                             scheduler=plan.scheduler, options=plan.report_options,
                             outputs=frame_outputs, render_one=plan.render_one,
                             render_many=_render_many(args, plan.config, plan.settings,
                                                      plan.render_one),
                             legend=plan.legend, rules=plan.rules)
    progression, checkpoints = start_progression(args, plan, outputs)
    replaced = [str(p) for p in outputs if p.exists()]  # before any checkpoint writes them
    previous = checkpoints.install_signal()
    try:
        result = plan.render_one(plan.config, plan.settings, progression=progression)
    except KeyboardInterrupt as stop:  # Ctrl-C and SIGTERM: the passes done are kept
        progression.interrupted()
        checkpoints.drain()  # a checkpoint under way first: then the latest
        stop.checkpointed = checkpoints.write()
        if stop.checkpointed and not args.quiet:
            print(f"interrupted after {progression.snapshot.passes_done} pass(es), "
                  f"{int(progression.film.count.max())} spp: wrote {', '.join(map(str, outputs))}"
                  f" and the checkpoint {checkpoints.path}; go on with --resume "
                  f"{checkpoints.path}", file=sys.stderr)
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGUSR1, previous)
    checkpoints.drain()  # no checkpoint is written after (or over) the final outputs
    image, error, report = finish_render(plan, result, outputs[0], args.reference)
    summary = summary_line(args, result, error, outputs, replaced)
    write_outputs(args, plan, outputs, result.film, image, report)
    checkpoints.finished()
    if not args.quiet:
        print(summary, file=sys.stderr)
        for line in recovery_lines(result.counters):  # a recovery is never silent
            print(line, file=sys.stderr)
    return 0


def write_outputs(args: argparse.Namespace, plan: RenderPlan, outputs: list[Path], film,
                  image: np.ndarray, report: dict) -> None:
    """Write the image (-o, --png) and the report, all or none: renamed into place together;
    where one cannot be written (a full disk...), all go to a rescue folder and the
    ``OutputError`` raised names it (``vastray.outputs``)."""
    depth, normal = film.depth_image(), film.normal_image()
    files = {outputs[0]: lambda path: write_image(path, image, depth, normal, args.exposure,
                                                  legend=plan.legend)}
    if args.png:
        files[Path(args.png)] = lambda path: write_png(path, image, args.exposure,
                                                       legend=plan.legend)
    if args.report:
        files[Path(args.report)] = lambda path: write_report(path, report)
    with StagedOutputs() as staged:
        staged.add(files)


def start_progression(args: argparse.Namespace, plan: RenderPlan, outputs: list[Path]
                      ) -> tuple[Progression, Checkpointer]:
    """The image's progression (from ``--resume`` where given) and its checkpoints, which
    write the film and the image so far (with a report that says where it stopped)."""
    camera = store_camera(plan.config, plan.store, plan.settings.width, plan.settings.height)
    identity = render_identity(plan.store, plan.config, camera, plan.settings,
                               plan.rules.max_pass_spp)
    resumed = read_checkpoint(args.resume, identity) if args.resume else None
    try:
        progression = plan.progression(resumed=resumed)
    except ValueError as exc:
        raise InputError(args.resume, str(exc)) from None

    def write_partial(progression: Progression) -> None:
        snap = progression.snapshot
        image = snap.film.image()
        report = build_report(
            store=str(plan.store_path), settings=asdict(plan.settings),
            seconds={"total": round(snap.seconds, 4)}, counters={}, scheduler=plan.scheduler,
            options=plan.report_options, progress=progression.report(),
            error=None if plan.reference is None else image_error(image, plan.reference),
            reference=args.reference if isinstance(args.reference, str) else None)
        report["checkpoint"] = str(checkpoints.path)
        write_outputs(args, plan, outputs, snap.film, image, report)

    argv = getattr(args, "argv", None)  # the CLI's arguments (the Python API has none)
    if argv is not None:  # so that `--resume CHECKPOINT` alone goes on with them
        identity = {**identity, "command": saved_command(argv, args.store)}
    checkpoints = Checkpointer(args.checkpoint or default_checkpoint(outputs[0]), identity,
                               args.checkpoint_every, write_partial)
    checkpoints.progression = progression
    progression.on_pass = checkpoints.after_pass
    return progression, checkpoints


def png_legend(args: argparse.Namespace, store: Store) -> Legend | None:
    """The colour bar PNGs get (None: not coloured by scalars, or not asked for: ``--legend``,
    by default on with ``--colormap``); checks
    the ``--colormap`` name first, so a wrong one is refused before any rendering."""
    if args.colormap is not None:
        colormap_lut(args.colormap)
    by_scalars = coloured_by_scalars(store)
    for option, given in (("--colormap", args.colormap is not None), ("--legend", args.legend),
                          ("--color-range", args.color_range is not None)):
        if given and not by_scalars:
            raise InputError(store.path, f"{option} is for a store coloured by its scalar field;"
                                         " this one has " + ("per-vertex colours" if
                                                             store.has_colors else "no scalars"))
    if args.legend and not (args.png or str(args.output).lower().endswith(".png")):
        raise InputError(None, "--legend draws into PNG output only: give --png FILE or a .png "
                               "-o")
    if args.color_range is not None and not args.color_range[0] < args.color_range[1]:
        raise InputError(None, f"--color-range LO HI needs LO < HI, got "
                               f"{args.color_range[0]:g} {args.color_range[1]:g}")
    wanted = args.legend if args.legend is not None else args.colormap is not None
    return legend_for(store, args.colormap, args.color_range and tuple(args.color_range)) \
        if wanted else None


def _renderer(args: argparse.Namespace, store: Store, store_path: Path, options: JobOptions,
              launched: dict | None) -> Callable[..., RenderResult]:
    """The job's scheduler as ``render_one(config, settings, progression=None) ->
    RenderResult``: the image in the passes ``progression`` asks for (None: in one pass),
    the result's ``progress`` its report. The distributed one also takes
    ``render_distributed``'s ``frames``, ``on_frame`` and ``progression_of``."""
    if args.nodes:
        def render_one(config, settings, progression=None, **frames):
            if progression is not None:
                frames["progression_of"] = lambda frame: progression
            return render_distributed(
                store_path, args.scene, settings, args.nodes, options,
                timeout=args.node_timeout, listen=args.listen,
                keys=load_coordinator_keys(args.keys) if args.keys else None,
                launched=launched,
                progress=not args.quiet, config=config, rendezvous=args.rendezvous,
                heartbeat_timeout=args.heartbeat_timeout, log_dir=node_log_dir(args),
                **frames)
    elif options.scheduler == "reference":
        kept = FrameCache(store, options.cache, options.load_bytes_per_second())

        def render_one(config, settings, progression=None):
            return _with_progress(render(
                store, config, settings, threads=options.threads, progress=not args.quiet,
                cache=kept.for_frame(config, settings.integrator), progression=progression),
                progression)
    else:
        def render_one(config, settings, progression=None):
            return _with_progress(render_out_of_core(
                store, config, settings, options, progress=not args.quiet,
                progression=progression), progression)
    return render_one


def node_log_dir(args: argparse.Namespace) -> Path | None:
    """Where the logs of the nodes started here are kept: ``--log-dir``, else beside
    ``--report`` (``REPORT.nodes``; the report names it), else nowhere (removed)."""
    if args.log_dir:
        return Path(args.log_dir)
    if args.report and not args.listen:
        return Path(f"{args.report}.nodes")
    return None


def _with_progress(result: RenderResult, progression: Progression | None) -> RenderResult:
    if progression is not None:
        result.progress = progression.report()
    return result


def _render_many(args: argparse.Namespace, config, settings: RenderSettings,
                 render_one: Callable[..., RenderResult]) -> Callable | None:
    """With ``--nodes``, where the distributed runtime renders several frames in one job:
    ``render_many(frames, on_frame, progression_of)`` (nodes started once, each frame's config and seed
    resolved on the nodes); else None, and each frame is a job of its own."""
    if not args.nodes:
        return None
    return lambda frames, on_frame, progression_of=None: render_one(
        config, settings, frames=frames, on_frame=on_frame, progression_of=progression_of)


def run_options(args: argparse.Namespace, options: JobOptions) -> dict:
    """The run's switches besides the scheduler, for its report (and ``vastray plot``'s
    labels): the job's options as the schedulers receive them (defaults filled in), the node
    count, timeouts and address, and the frames."""
    report = options.for_report()
    del report["scheduler"]  # the report's own "scheduler"
    nodes = {"node_timeout_s": args.node_timeout, "heartbeat_timeout_s": args.heartbeat_timeout,
             "listen": args.listen} if args.nodes else {}
    return {"nodes": args.nodes, **report, **nodes, "frames": args.frames,
            "first_frame": args.first_frame, "memory_limit": args.memory_limit}


def _check_render_memory(args: argparse.Namespace, config, scheduler: str, store: Store,
                         cache: int | None) -> tuple[int | None, RenderMemory]:
    """Refuse up front a render that cannot fit in memory (``preflight.check_memory``: every
    process it starts here, less a margin for the rest of the machine); with
    ``--memory-limit``, first bound each process's domain cache by what its base, film and
    paths in flight leave. Returns the cache and the estimates."""
    # shadow rays per hit: AO's samples, or per light its samples (area and sky) or one
    rays_per_hit = args.shadow_samples if args.integrator == "ao" else max(sum(
        shadow_rays(light, args.shadow_samples) for light in config.resolve_lights()), 1)
    threads = args.threads or available_cpus()
    total = args.width * args.height * args.spp
    footprints = domain_footprints(store.domains)
    reference = args.reference is not None  # a file name, or an array (the Python API)

    @functools.cache
    def copies() -> float:
        """spec-ooc's speculative copies of each shadow ray, beyond the model's own."""
        lo, hi = store.domain_boxes()
        return speculative_copies(
            crossings_from_surface(lo, hi, [d.n_triangles for d in store.domains]),
            args.bounces + 1 if args.integrator == "pt" else 1)

    def process(cache: int | None) -> MemoryEstimate:
        """One rendering process (a node with --nodes), its domains left out."""
        if args.nodes:
            tile = args.max_samples_in_flight or DEFAULT_NODE_SAMPLES_IN_FLIGHT
            return estimate_memory(args.width, args.height, min(tile, total), rays_per_hit,
                                   role="node",
                                   copies=copies() if scheduler == "spec-ooc" else 0.0)
        all_fit = cache is None or cache >= len(footprints)
        if scheduler == "reference" and (all_fit or args.scheduler != "auto"):
            in_flight = reference_paths_in_flight(total, args.batch_size or DEFAULT_BATCH_SIZE,
                                                  threads, all_fit)
        else:  # out of core (auto becomes spec-ooc when the domains do not all fit)
            in_flight = min(args.max_samples_in_flight or DEFAULT_SAMPLES_IN_FLIGHT, total)
            if args.scheduler in ("spec-ooc", "auto"):
                return estimate_memory(args.width, args.height, in_flight, rays_per_hit,
                                       reference=reference, copies=copies())
        return estimate_memory(args.width, args.height, in_flight, rays_per_hit,
                               reference=reference)

    if args.memory_limit is not None:
        if not args.listen:  # the processes it bounds run here
            check_limit_fits_machine(args.memory_limit)
        if scheduler == "spec-insitu":  # no cache to bound: every node's own domains must fit
            from vastray.schedule.ownership import zorder_owners

            nodes = args.nodes or 1
            check_owned_fit(args.memory_limit, process(cache), footprints,
                            zorder_owners(*store.domain_boxes(), nodes), nodes)
        else:
            fitting = cache_within(args.memory_limit, process(cache), footprints,
                                   args.width, args.height)
            if fitting < len(footprints) and args.scheduler == "auto":  # becomes spec-ooc
                fitting = cache_within(args.memory_limit, process(fitting), footprints,
                                       args.width, args.height)
            log.info("--memory-limit leaves room for %d domains per process", fitting)
            cache = fitting if cache is None else min(cache, fitting)
    held = sum(sorted(footprints, reverse=True)[:cache or len(footprints)])
    one = process(cache) + MemoryEstimate(0, 0, 0, domains=held)
    coordinator, machine = None, one
    if args.nodes:  # the coordinator, and every node unless they run elsewhere
        coordinator = estimate_memory(args.width, args.height, 0, 0, role="coordinator",
                                      reference=reference)
        machine = coordinator if args.listen else coordinator + one.times(args.nodes)
    check_memory(machine, args.width, args.height)
    return cache, RenderMemory(one, coordinator, machine)


def summary_line(args: argparse.Namespace, result, error: dict | None,
                 outputs: list[Path], replaced: list[str] | None = None) -> str:
    """The last line of a render: every file written, the work, the time and the error."""
    seconds = max(result.seconds["total"], 1e-9)
    queries = ray_queries(result.counters)
    line = (f"wrote {', '.join(map(str, outputs))} ({args.width}x{args.height}, {args.spp} spp, "
            f"{args.integrator}) in {seconds:.2f} s")
    if queries:
        line += f", {queries[1] / seconds / 1e6:.2f} M {queries[0]}/s"
    line += f", {result.counters.get('loads', 0)} domain loads"
    if result.counters.get("bytes_loaded"):  # out of core: what loading cost
        line += (f" ({result.counters['bytes_loaded'] / 1e9:.2f} GB read, "
                 f"{result.counters.get('load_wait_s', 0.0):.1f} s waited)")
    peak = result.counters.get("peak_rss_bytes") or result.counters.get("peak_rss_bytes_max")
    if args.memory_limit is not None and peak:  # the busiest process against its limit
        line += f", peak RSS {gigabytes(peak)} of --memory-limit {gigabytes(args.memory_limit)}"
    if error is not None:
        psnr = "inf" if error["psnr_db"] is None else f"{error['psnr_db']:.2f}"
        line += f", MSE {error['mse']:.4g}, PSNR {psnr} dB"
    if replaced is None:  # made before the outputs are written
        replaced = [str(p) for p in outputs if p.exists()]
    progress = result.progress or {}
    if progress.get("stopped_by") not in (None, "spp"):
        line += (f"; stopped by --{progress['stopped_by']} at "
                 f"{progress['passes'][-1]['spp']} spp")
    if replaced:  # the files a user names are replaced, as renderers do, but never silently
        line += f"; replaced the existing {', '.join(replaced)}"
    return line


def ray_queries(counters: dict) -> tuple[str, int] | None:
    """What the run counted of its Embree work: ("rays", n) for the reference renderer, which
    traces each ray once through all its domains, ("ray-domain queries", n) for schedules
    that query domain by domain (summed over nodes); None when nothing was counted."""
    if "rays" in counters:
        return "rays", int(counters["rays"]["total"])
    parts = [counters] + [node.get("counters", {}) for node in counters.get("per_node", [])]
    total = sum(int(part.get("radiance_tests", 0)) + int(part.get("shadow_tests", 0))
                for part in parts)
    return ("ray-domain queries", total) if total else None


def run_compare(args: argparse.Namespace) -> int:
    image, reference = read_image(args.image), read_image(args.reference)
    if image.shape != reference.shape:
        raise InputError(args.image, f"size {image.shape} differs from the reference's "
                                     f"{reference.shape}")
    err = image_error(image, reference)
    psnr = "inf" if err["psnr_db"] is None else f"{err['psnr_db']:.3f}"
    print(f"mse={err['mse']:.6g} psnr_db={psnr} max_abs_diff={err['max_abs_diff']:.6g}")
    return 0
