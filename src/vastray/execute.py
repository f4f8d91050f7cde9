"""A ``RenderRequest`` run to its files, as ``vastray render`` runs it: outputs checked first,
the plan (``planning.plan_render``), the image's passes with their checkpoints (or an
animation's frames), then the image, PNG and report written all or none, and the last line."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from vastray.actors.results import closing_lines
from vastray.animation import check_frame_outputs, reference_path, run_animation
from vastray.checkpoint import Checkpointer, read_checkpoint, render_identity, saved_command
from vastray.checkpoint import default_path as default_checkpoint
from vastray.outputs import StagedOutputs
from vastray.planning import RenderPlan, finish_render, plan_render, traces_passes_ahead
from vastray.preflight import (
    check_inputs_spared,
    check_output_paths,
    check_writable_place,
    gigabytes,
)
from vastray.render.driver import RenderResult, store_camera
from vastray.render.imageio import image_error, write_image, write_png
from vastray.render.integrators import RenderSettings
from vastray.render.progressive import Progression
from vastray.report import build_report, write_report
from vastray.request import RenderRequest
from vastray.scene.errors import InputError

log = logging.getLogger(__name__)


def run(request: RenderRequest, launched: dict | None = None) -> int:
    """Render ``request`` to its files; returns the exit status (0). ``launched``: node
    processes started elsewhere (``vastray launch``)."""
    request = request.resolved()
    animating = request.frames is not None or request.first_frame is not None
    if animating:
        first = request.first_frame or 0
        frames = list(range(first, first + (request.frames or 1)))
        frame_outputs = check_frame_outputs(request.output, request.png, request.report, frames)
        check_inputs_spared(
            [*(p for f in frames for p in frame_outputs.of(f)),
             *([Path(request.report)] if request.report else [])], request.store,
            [reference_path(request.reference, f) for f in frames]
            if isinstance(request.reference, str) else [])
    else:
        outputs = check_output_paths(request.output, request.png, request.report)
        check_inputs_spared(outputs, request.store,
                            [Path(request.reference)] if isinstance(request.reference, str) else [],
                            checkpoint_path(request), request.resume)
    if request.rendezvous:
        check_writable_place(Path(request.rendezvous), "--rendezvous")
    plan = plan_render(request, animating=animating, launched=launched)
    if animating:
        return run_animation(request, store_path=str(plan.store_path), config=plan.config,
                             settings=plan.settings, bounds=plan.store.world_bounds,
                             scheduler=plan.scheduler, options=plan.report_options,
                             outputs=frame_outputs, render_one=plan.render_one,
                             render_many=_render_many(request, plan.config, plan.settings,
                                                      plan.render_one),
                             legend=plan.legend, rules=plan.rules)
    progression, checkpoints = start_progression(request, plan, outputs)
    if plan.rules.one_pass and not request.quiet:
        print(f"passes: one of {plan.settings.spp} spp (out of core, every pass would reload "
              "what the cache lost, and nothing reads the image between passes; --reference, "
              "--time-limit, --target-error, --checkpoint-every or --max-pass-spp renders in "
              "passes)", file=sys.stderr)
    ahead = traces_passes_ahead(plan)
    if ahead is not None and not request.quiet:
        print("passes: apart, out of core, " + (
            "the next passes traced on the current one's domain loads (each pass's image "
            "still merged as it ends" + ("; only passes --time-limit's rule may still grant"
                                         if request.time_limit is not None else "") + ")"
            if ahead else "each sweeping the domains alone (--passes-alone)"), file=sys.stderr)
    replaced = [str(p) for p in outputs if p.exists()]  # before any checkpoint writes them
    previous = checkpoints.install_signal()
    try:
        result = plan.render_one(plan.config, plan.settings, progression=progression)
    except KeyboardInterrupt as stop:  # Ctrl-C and SIGTERM: the passes done are kept
        progression.interrupted()
        checkpoints.uninstall_signal(previous)  # a SIGUSR1 write under way ends first
        previous = None
        checkpoints.drain()  # a checkpoint under way first: then the latest
        stop.checkpointed = checkpoints.write()
        if not stop.checkpointed and not request.quiet and plan.rules.one_pass:
            print("interrupted during the one pass: nothing finished to keep (render with "
                  "--checkpoint-every SECONDS to keep the passes done)", file=sys.stderr)
        if stop.checkpointed and not request.quiet:
            print(f"interrupted after {progression.snapshot.passes_done} pass(es), "
                  f"{int(progression.film.count.max())} spp: wrote {', '.join(map(str, outputs))}"
                  f" and the checkpoint {checkpoints.path}; go on with --resume "
                  f"{checkpoints.path}", file=sys.stderr)
        raise
    finally:
        checkpoints.uninstall_signal(previous)
    checkpoints.drain()  # no checkpoint is written after (or over) the final outputs
    image, error, report = finish_render(plan, result, outputs[0], request.reference)
    summary = summary_line(request, result, error, outputs, replaced)
    write_outputs(request, plan, outputs, result.film, image, report)
    checkpoints.finished()
    if not request.quiet:
        print(summary, file=sys.stderr)
        for line in closing_lines(result.counters, result.seconds):
            print(line, file=sys.stderr)
    return 0


def write_outputs(request: RenderRequest, plan: RenderPlan, outputs: list[Path], film,
                  image: np.ndarray, report: dict) -> None:
    """Write the image (-o, --png) and the report, all or none: renamed into place together;
    where one cannot be written (a full disk...), all go to a rescue folder and the
    ``OutputError`` raised names it (``vastray.outputs``)."""
    depth, normal = film.depth_image(), film.normal_image()
    files = {outputs[0]: lambda path: write_image(path, image, depth, normal, request.exposure,
                                                  legend=plan.legend)}
    if request.png:
        files[Path(request.png)] = lambda path: write_png(path, image, request.exposure,
                                                       legend=plan.legend)
    if request.report:
        files[Path(request.report)] = lambda path: write_report(path, report)
    with StagedOutputs() as staged:
        staged.add(files)


def start_progression(request: RenderRequest, plan: RenderPlan, outputs: list[Path]
                      ) -> tuple[Progression, Checkpointer]:
    """The image's progression (from ``--resume`` where given) and its checkpoints, which
    write the film and the image so far (with a report that says where it stopped)."""
    camera = store_camera(plan.config, plan.store, plan.settings.width, plan.settings.height)
    identity = render_identity(plan.store, plan.config, camera, plan.settings,
                               plan.rules.max_pass_spp)
    resumed = read_checkpoint(request.resume, identity) if request.resume else None
    try:
        progression = plan.progression(resumed=resumed)
    except ValueError as exc:
        raise InputError(request.resume, str(exc)) from None

    def write_partial(progression: Progression) -> None:
        snap = progression.snapshot
        image = snap.film.image()
        report = build_report(
            store=str(plan.store_path), settings=asdict(plan.settings),
            seconds={"total": round(snap.seconds, 4)}, counters={}, scheduler=plan.scheduler,
            options=plan.report_options, progress=progression.report(),
            error=None if plan.reference is None else image_error(image, plan.reference),
            reference=request.reference if isinstance(request.reference, str) else None)
        report["checkpoint"] = str(checkpoints.path)
        write_outputs(request, plan, outputs, snap.film, image, report)

    if request.argv is not None:  # the CLI's: so that `--resume CHECKPOINT` alone goes on with them
        identity = {**identity, "command": saved_command(list(request.argv), request.store)}
    checkpoints = Checkpointer(checkpoint_path(request), identity, request.checkpoint_every,
                               write_partial)
    checkpoints.progression = progression
    progression.on_pass = checkpoints.after_pass
    return progression, checkpoints


def checkpoint_path(request: RenderRequest) -> Path:
    """Where the render's checkpoints go: ``--checkpoint``, else ``-o``'s name +
    ``.checkpoint.npz``."""
    return Path(request.checkpoint) if request.checkpoint else default_checkpoint(request.output)


def _render_many(request: RenderRequest, config, settings: RenderSettings,
                 render_one: Callable[..., RenderResult]) -> Callable | None:
    """With ``--nodes``, where the distributed runtime renders several frames in one job:
    ``render_many(frames, on_frame, progression_of)`` (nodes started once, each frame's config and seed
    resolved on the nodes); else None, and each frame is a job of its own."""
    if not request.nodes:
        return None
    return lambda frames, on_frame, progression_of=None: render_one(
        config, settings, frames=frames, on_frame=on_frame, progression_of=progression_of)


def summary_line(request: RenderRequest, result, error: dict | None,
                 outputs: list[Path], replaced: list[str] | None = None) -> str:
    """The last line of a render: every file written, the work, the time and the error."""
    seconds = max(result.seconds["total"], 1e-9)
    queries = ray_queries(result.counters)
    line = (f"wrote {', '.join(map(str, outputs))} ({request.width}x{request.height}, {request.spp} spp, "
            f"{request.integrator}) in {seconds:.2f} s")
    if queries:
        line += f", {queries[1] / seconds / 1e6:.2f} M {queries[0]}/s"
    line += f", {result.counters.get('loads', 0)} domain loads"
    if result.counters.get("bytes_loaded"):  # out of core: what loading cost
        line += (f" ({result.counters['bytes_loaded'] / 1e9:.2f} GB read, "
                 f"{result.counters.get('load_wait_s', 0.0):.1f} s waited)")
    peak = result.counters.get("peak_rss_bytes") or result.counters.get("peak_rss_bytes_max")
    if request.memory_limit is not None and peak:  # the busiest process against its limit
        line += f", peak RSS {gigabytes(peak)} of --memory-limit {gigabytes(request.memory_limit)}"
        held = result.counters.get("peak_resident_domains")
        if held and not request.nodes:  # what the limit bought: the cache is bounded by bytes
            line += f" ({held} of {result.counters.get('domains', '?')} domains held at most)"
    if error is not None:
        psnr = "inf" if error["psnr_db"] is None else f"{error['psnr_db']:.2f}"
        line += f", MSE {error['mse']:.4g}, PSNR {psnr} dB"
    if replaced is None:  # made before the outputs are written
        replaced = [str(p) for p in outputs if p.exists()]
    progress = result.progress or {}
    if progress.get("stopped_by") not in (None, "spp"):
        line += (f"; stopped by --{progress['stopped_by']} at "
                 f"{progress['passes'][-1]['spp']} spp")
    elif request.target_error is not None and progress.get("stopped_by") == "spp":
        line += f"; --target-error {request.target_error:g} not reached by --spp {request.spp}"
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
