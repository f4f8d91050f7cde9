"""``vastray render``: its options, and the render of a command line to files."""

from __future__ import annotations

import argparse
import logging

from vastray.actors.job_options import MAX_JOB_TILE, MIN_NODE_SHARE
from vastray.execute import run
from vastray.render.progressive import DEFAULT_MAX_PASS_SPP
from vastray.request import (
    BUILTIN_DEFAULTS,
    DEFAULT_BATCH_SIZE,
    DEFAULT_EXPOSURE,
    DEFAULT_HEARTBEAT_TIMEOUT_S,
    DEFAULT_NODE_SAMPLES_IN_FLIGHT,
    DEFAULT_NODE_TIMEOUT_S,
    DEFAULT_PORTAL_INTERVAL,
    DEFAULT_PORTAL_THRESHOLD,
    DEFAULT_SAMPLES_IN_FLIGHT,
    STORE_DEFAULTS,
    RenderRequest,
    argument,
)
from vastray.scene.bvh_choice import FAST_TRIANGLES

log = logging.getLogger(__name__)

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


def add_render_arguments(p: argparse.ArgumentParser) -> None:
    """The options shared by ``render`` and ``launch``."""
    p.add_argument("store", **argument("store"),
                   help="STORE folder (default: the built-in scene)")
    p.add_argument("-o", "--output", **argument("output"), required=True,
                   help="output image; the extension picks the format: .exr (float RGB plus "
                        "depth and normal layers), .pfm, .hdr or .png. Like --png and "
                        "--report, an existing file is replaced (the last line says so)")
    p.add_argument("--png", **argument("png"), help="also write a tone-mapped PNG preview")
    p.add_argument("--scene", **argument("scene"), help="SCENE.toml with camera, lights and materials")
    p.add_argument("--integrator", **argument("integrator"),
                   help="ambient occlusion or path tracing (default: pt)")
    p.add_argument("--spp", **argument("spp"),
                   help=f"samples per pixel (default: {STORE_DEFAULTS['spp']}; "
                        f"{BUILTIN_DEFAULTS['spp']} for the built-in scene)")
    p.add_argument("--bounces", **argument("bounces"),
                   help=f"diffuse bounces for pt (default: {STORE_DEFAULTS['bounces']}, as in "
                        f"the SpRay paper; {BUILTIN_DEFAULTS['bounces']} for the built-in scene)")
    p.add_argument("--shadow-samples", **argument("shadow_samples"),
                   help="shadow rays per hit toward each area/ambient light, and AO rays per "
                        f"hit (default: {STORE_DEFAULTS['shadow_samples']}; "
                        f"{BUILTIN_DEFAULTS['shadow_samples']} for the built-in scene)")
    p.add_argument("--ao-distance", **argument("ao_distance"),
                   help="AO ray length (default: a tenth of the scene diagonal)")
    p.add_argument("--width", **argument("width"),
                   help=f"image width (default: {STORE_DEFAULTS['width']}; "
                        f"{BUILTIN_DEFAULTS['width']} for the built-in scene)")
    p.add_argument("--height", **argument("height"),
                   help=f"image height (default: {STORE_DEFAULTS['height']}; "
                        f"{BUILTIN_DEFAULTS['height']} for the built-in scene)")
    p.add_argument("--seed", **argument("seed"),
                   help="random seed (default: 0)")
    p.add_argument("--bvh", **argument("bvh"),
                   help="the BVH Embree builds for each domain: 'quality' (Embree's default "
                        "build: the fastest to trace), 'fast' (Embree's Morton builder over its "
                        "compact layout: about 3x faster to build, 55%% of the memory, slower "
                        "to trace (the builder 5-30%%, the layout 20-30%% more); for data "
                        "loaded more than once, out of core) or "
                        "'auto' (default: fast for stores of "
                        f"{FAST_TRIANGLES // 1_000_000} M triangles or more). The two find "
                        "another hit for a few rays passing within rounding of a vertex, so "
                        "the choice is the store's, never the cache's: an image is the same "
                        "whatever the cache and the node count")
    p.add_argument("--cache", **argument("cache"), metavar="N|P%",
                   help="most domains in memory at once, as a count or a percentage of the "
                        "domains (default: all)")
    p.add_argument("--scheduler", **argument("scheduler"),
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
    p.add_argument("--memory-limit", **argument("memory_limit"), metavar="SIZE",
                   help="most memory each process (each node) may use, e.g. 8G or 700M (K, M, G, "
                        "T: KiB, MiB, GiB, TiB): bounds the bytes of its "
                        "domain cache by what the rest of the process leaves (interpreter and "
                        "libraries, film, paths in flight, and a 75 MB margin for the "
                        "libraries' measured spread), so it holds as many domains as fit, "
                        "small ones more (cache_bytes in the report); above 90%% of it a cache gives the "
                        "heap's free memory back before each domain build (heap_trims in the "
                        "report); the report's peak_rss_bytes is the "
                        "measured peak; a render that cannot fit is "
                        "refused before it starts (default: a render is refused only when it "
                        "needs more than 85%% of the available memory)")
    p.add_argument("--max-samples-in-flight", **argument("max_samples_in_flight"), metavar="N",
                   help="out-of-core (image, spec-ooc) and every --nodes scheduler: paths "
                        "traced at once; bounds the rays held in memory (default: "
                        f"{DEFAULT_SAMPLES_IN_FLIGHT}; with --nodes, "
                        f"{DEFAULT_NODE_SAMPLES_IN_FLIGHT}: each node's own for image and "
                        "spec-ooc, shared by the nodes for the domain-decomposition "
                        "schedulers, whose nodes hold the rays waiting for their domains, "
                        f"and past 16 nodes {MIN_NODE_SHARE} a node, at most {MAX_JOB_TILE})")
    p.add_argument("--history-depth", **argument("history_depth"), metavar="H",
                   help="spec-ooc: bounces speculated before hits are resolved "
                        "(default: --bounces, the most aggressive)")
    p.add_argument("--nodes", **argument("nodes"), metavar="N",
                   help="render with N node processes on this machine, talking ZeroMQ over "
                        "loopback: image and spec-ooc give each node a band of the image, "
                        "or tiles of --max-samples-in-flight paths round robin on a larger "
                        "frame, each traced by its node alone (sort-first); "
                        "domain, async, dynamic, spec-insitu and temporal split the domains "
                        "(see --scheduler)")
    p.add_argument("--node-timeout", **argument("node_timeout"), metavar="S",
                   help=f"with --nodes: fail when a node is silent this long (default: "
                        f"{DEFAULT_NODE_TIMEOUT_S:g})")
    p.add_argument("--log-dir", **argument("log_dir"), metavar="DIR",
                   help="with --nodes (started here): keep each node's log in DIR "
                        "(nodeR.log: its failures and the messages and connections it "
                        "refused); default: beside --report as REPORT.nodes, else removed "
                        "when the render ends")
    p.add_argument("--heartbeat-timeout", **argument("heartbeat_timeout"), metavar="S",
                   help="with --nodes: a node silent this long mid-frame is lost (stalled); "
                        "it is survived by rendering the frame again on the others (with "
                        f"--listen, once they have joined again) (default: {DEFAULT_HEARTBEAT_TIMEOUT_S:g})")
    p.add_argument("--listen", **argument("listen"), metavar="HOST:PORT",
                   help="with --nodes N: wait for N nodes started elsewhere (`vastray node "
                        "--coordinator tcp://HOST:PORT`, docker compose, SSH) instead of "
                        "starting them here")
    p.add_argument("--rendezvous", **argument("rendezvous"), metavar="FILE",
                   help="with --listen: write this coordinator's address into FILE on a file "
                        "system the nodes share, for `vastray node --rendezvous FILE` under "
                        "srun or mpirun (`vastray node --help` shows a Slurm job)")
    p.add_argument("--keys", **argument("keys"), metavar="DIR",
                   help="with --listen: the key folder from `vastray keys` (ZeroMQ CURVE: "
                        "encrypted; a node joins only with its own key on DIR/public's "
                        "allow-list); needed to listen beyond loopback. Without it only nodes "
                        "of your user on this machine may join")
    p.add_argument("--no-preload", **argument("no_preload"),
                   help="do not load the next domain in the background (every scheduler with "
                        "a cache; the 'no preloading' rows of the benchmarks)")
    p.add_argument("--assignment", **argument("assignment"),
                   help="async/temporal: which node owns which domain: round robin "
                        "(sequential; async's default), contiguous z-order runs (spatial), "
                        "the temporal-coherence paper's Algorithm 1 from the last frame's ray "
                        "transmissions (paper), or Algorithm 1 where a domain a node holds "
                        "stays there unless moving it saves more than its load (affinity; "
                        "temporal's default), or spatial while every node's group fits its "
                        "cache and affinity where it does not (fit). Frame 0 uses spatial "
                        "for all three")
    p.add_argument("--priority", **argument("priority"),
                   help="temporal: how a node picks the next domain and what it preloads: "
                        "most queued rays (queue), SpRay's traversal score, queued plus "
                        "expected rays from the active domain (queue+act), the paper's "
                        "cost-benefit Eq. 1 as written (predicted work minus load time), "
                        "cost-rate (default: Eq. 1's predicted work per second of loading, so "
                        "cached domains go first), or queue+resident (most queued rays, cached "
                        "domains first: the queue baseline made cache-aware)")
    p.add_argument("--simplified", **argument("simplified"), metavar="POLICY",
                   help="async/temporal: trace some rays on the store's simplified model "
                        "(`vastray simplify STORE --ratio 0.01`) held by every node, never "
                        "sending them between nodes: 'portal' (default) sends depth-1 rays "
                        "whose virtual portal predicts little light, and every deeper ray; "
                        "'depth>K' every ray deeper than K; 'none' nothing. Lossy: compare "
                        "with --reference")
    p.add_argument("--portal-interval", **argument("portal_interval"), metavar="N",
                   help=f"--simplified portal: record the portals every N frames (default "
                        f"{DEFAULT_PORTAL_INTERVAL})")
    p.add_argument("--portal-memory", **argument("portal_memory"), metavar="N",
                   help="--simplified portal: frames between recording frames record too, "
                        "from the depth-1 rays they trace fine, and a cell no frame has "
                        "recorded for N frames is forgotten (default: off, the paper's: only "
                        "every --portal-interval-th frame records). Fills the portals of "
                        "small frames, whose few paths leave most cells unrecorded")
    p.add_argument("--portal-resolution", **argument("portal_resolution"), metavar="R",
                   help="--simplified portal: cells per portal edge, R x R x 8 directions on "
                        "each domain face (default 32, the paper's; its Table 4 sweeps "
                        "8-128). Coarser portals fill with fewer paths: at small images most "
                        "crossings of a 32 x 32 portal land in cells no path has recorded, "
                        "which are traced fine")
    p.add_argument("--portal-threshold", **argument("portal_threshold"), metavar="L",
                   help="--simplified portal: predicted radiance at or below which a depth-1 "
                        f"ray goes to the simplified model (default {DEFAULT_PORTAL_THRESHOLD})")
    p.add_argument("--portal-accuracy", **argument("portal_accuracy"),
                   help="--simplified portal: an instrumented run for evaluation, not for "
                        "timing: every frame is traced as a recording frame (every depth-1 "
                        "ray on the full model) and each depth-1 portal crossing is "
                        "classified with the portals a timed run would predict it with; each "
                        "frame's report gets acc (the paper's prediction accuracy), "
                        "acc_simplified_share, acc_unrecorded_share and replay_false_low")
    p.add_argument("--load-bandwidth", **argument("load_bandwidth"), metavar="MB/s[,MB/s...]",
                   help="emulate network storage, for every scheduler: a domain load takes at "
                        "least its size over this bandwidth (per process; with --nodes a list "
                        "is cycled over the ranks); an emulation by waiting after the real "
                        "read, for benchmarks. The report gives bytes_loaded and "
                        "load_throttle_s, the time spent waiting")
    p.add_argument("--cold-reads", **argument("cold_reads"),
                   help="out of core (image, spec-ooc and the node schedulers with a cache): "
                        "drop each domain's files from the page cache as they are read "
                        "(posix_fadvise DONTNEED), so every reload after an eviction is a real "
                        "disk read; the report gives bytes_loaded, load_s and load_wait_s, the "
                        "time the renderer waited on loads")
    p.add_argument("--eviction", **argument("eviction"),
                   help="image and spec-ooc: which domain a load evicts: the least recently "
                        "used (lru, default) or the one the schedule will need last by its "
                        "own order (demand: the emptiest queue for image, the latest in the "
                        "round for spec-ooc; an approximation of Belady's rule); the report's "
                        "belady_loads is the fewest loads the run's own domain order allows")
    p.add_argument("--batch-size", **argument("batch_size"),
                   help="in-core reference render: paths traced together (default: "
                        f"{DEFAULT_BATCH_SIZE}; cut finer when a frame has fewer than two "
                        "batches per render worker)")
    p.add_argument("--threads", **argument("threads"),
                   help="threads per process (default: the cores it may use, its CPU affinity "
                        "and cgroup CPU quota (docker --cpus); with --nodes N on this machine, "
                        "those / N per node; with --listen, each node's own). In "
                        "core, one render worker per thread traces batches side by side; out of "
                        "core, each Embree query splits its rays over the threads")
    p.add_argument("--report", **argument("report"), help="write a JSON report (timings, counts, error)")
    p.add_argument("--reference", **argument("reference"),
                   help="reference image (.exr/.pfm/.npy) to report MSE, PSNR and relative MSE "
                        "against; with --frames, a pattern such as ref_{frame:04d}.exr or a "
                        "plain name ref.exr meaning ref_0000.exr, ref_0001.exr ...")
    p.add_argument("--frames", **argument("frames"), metavar="N",
                   help="render an animation of N frames (moved by the scene's "
                        "[[camera.key]], [camera.orbit], [[light.key]] or light move); -o "
                        "a.exr writes "
                        "a_0000.exr, a_0001.exr ..., as do --png and --report, and the "
                        "--report path gets a summary of every frame. Frame f uses the seed "
                        "hash(--seed, f) (default: one image, no numbering, the seed as given)")
    p.add_argument("--first-frame", **argument("first_frame"), metavar="F",
                   help="the first frame's number (default: 0); without --frames, "
                        "renders that one frame (numbered outputs, its own seed)")
    p.add_argument("--exposure", **argument("exposure"),
                   help=f"PNG exposure multiplier, for --png or a .png -o (default: {DEFAULT_EXPOSURE:g})")
    p.add_argument("--colormap", **argument("colormap"), metavar="NAME",
                   help="matplotlib colour map for a store coloured by its scalar field, e.g. "
                        "viridis, plasma, coolwarm, turbo (needs matplotlib: pip install "
                        "'vastray[plot]'; default: a built-in viridis)")
    p.add_argument("--color-range", **argument("color_range"), metavar=("LO", "HI"),
                   help="map scalars LO..HI to the colour map's ends, whatever the store's "
                        "range (ParaView's custom range), so renders of different data, every "
                        "frame and every node share one scale (default: the store's range)")
    p.add_argument("--legend", **argument("legend"),
                   help="draw a colour bar (the scalar's name and range) along the bottom of "
                        "the PNG of a store coloured by scalars (default: with --colormap)")
    p.add_argument("--quiet", **argument("quiet"),
                   help="no progress bar")
    passes = p.add_argument_group(
        "progressive passes, stopping rules and checkpoints",
        "Every render runs in sample-major passes: pass k adds samples to every pixel "
        "(1, 1, 2, 4, 8, ... per pixel, then at most --max-pass-spp), so the image after any "
        "pass is the whole image at fewer samples, the same whatever the scheduler or node "
        "count. The report's 'passes' gives each pass's time, spp, error against "
        "--reference (MSE, relMSE, PSNR) and the film's own variance estimate and 95% "
        "confidence interval; `vastray plot` draws them. --spp is the upper bound. Out of "
        "core, where nothing reads the image between passes, the render is one pass; with "
        "--reference, --target-error or --time-limit each pass still ends on its own, the "
        "next passes traced on its domain loads (under --time-limit, those its rule may "
        "still grant).")
    passes.add_argument("--passes-alone", **argument("passes_alone"),
                        help="out of core with passes apart: each pass sweeps the domains "
                             "alone, not traced ahead on the one before (each pass's error "
                             "as early as it can come, at more domain loads; the 'alone' "
                             "rows of bench/ooc.py)")
    passes.add_argument("--time-limit", **argument("time_limit"), metavar="SECONDS",
                        help="stop before a pass that would end after SECONDS of rendering "
                             "(predicted from the pass before; the first pass always runs)")
    passes.add_argument("--target-error", **argument("target_error"), metavar="E",
                        help="stop after the pass whose relative MSE is at most E: against "
                             "--reference, or without one as the film estimates it from its "
                             "own variance (from 2 spp on), e.g. 0.01")
    passes.add_argument("--max-pass-spp", **argument("max_pass_spp"), metavar="N",
                        help=f"most samples per pixel one pass adds (default: "
                             f"{DEFAULT_MAX_PASS_SPP}): smaller gives more points and "
                             "checkpoints, larger less overhead per pass")
    passes.add_argument("--checkpoint-every", **argument("checkpoint_every"), metavar="SECONDS",
                        help="every SECONDS (at the end of a pass), write the image so far to "
                             "-o (and --png) and the film to --checkpoint. SIGUSR1 writes one "
                             "at once; Ctrl-C writes one before exiting. A run that completes "
                             "removes the checkpoint it wrote")
    passes.add_argument("--checkpoint", **argument("checkpoint"), metavar="FILE",
                        help="where checkpoints go (default: -o's name + .checkpoint.npz)")
    passes.add_argument("--resume", **argument("resume"), metavar="CHECKPOINT",
                        help="go on from a checkpoint: `vastray render --resume FILE` alone "
                             "runs the command that wrote it again (kept in it), with what "
                             "else you type on top (--spp may be larger; any --nodes and "
                             "lossless scheduler); given a STORE, it takes the options typed "
                             "now. The image is the one an uninterrupted run gives")


def run_render(args: argparse.Namespace, launched: dict | None = None) -> int:
    """``vastray render``: its command line as a ``RenderRequest``, rendered to its files."""
    return run(RenderRequest.from_namespace(args), launched)
