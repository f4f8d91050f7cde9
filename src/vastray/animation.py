"""Animations: ``vastray render --frames N`` renders frames F, F+1, ..., F+N-1 of a scene whose
camera and lights move (``[[camera.key]]``, ``[camera.orbit]``, ``[[light.key]]``, ``move``;
see ``vastray.render.scene_config``).

Frame f is the scene's config resolved at f (``SceneConfig.at_frame``) rendered with the seed
``frame_seed(seed, f)``: frames are independent Monte Carlo samples, and each is a pure
function of (scene, settings, seed, f), so a lossless scheduler's frames equal the
single-process frames, and a frame renders the same alone or in a sequence.

Outputs are numbered: ``-o anim.exr`` writes ``anim_0000.exr``, ``anim_0001.exr`` ...; so do
``--png`` and ``--report``, and the ``--report`` path itself receives a summary of every frame.
Every output of every frame is checked before the first frame starts; all are written to
temporary names beside their final ones as the frames finish and renamed together when the
last frame is done, so a failed animation leaves no file. An interrupted one (Ctrl-C, SIGTERM)
keeps the frames it finished: their files are renamed into place, each frame whole, and the
last line names them.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from vastray.actors.results import recovery_lines
from vastray.outputs import StagedOutputs
from vastray.preflight import check_output_paths
from vastray.render.driver import RenderResult
from vastray.render.imageio import image_error, read_image, write_image, write_png
from vastray.render.integrators import RenderSettings
from vastray.render.progressive import Progression, StopRules
from vastray.render.rng import frame_seed
from vastray.render.scene_config import SceneConfig
from vastray.report import build_report, count_overflow, run_header, write_report
from vastray.scene.errors import InputError
from vastray.scene.filemode import publish_mode

log = logging.getLogger(__name__)

#: ``render_one(config, settings, progression=None) -> RenderResult``: one frame, its config
#: already resolved and its settings already carrying the frame's seed, in the passes of
#: ``progression`` (``render.progressive``).
RenderOne = Callable[..., RenderResult]
#: ``render_many(frames, on_frame, progression_of)``: every frame in one job (the distributed
#: runtime), calling ``on_frame(frame, result)`` as each frame's film arrives.
RenderMany = Callable[..., object]


def frame_path(path: str | Path, frame: int) -> Path:
    """``anim.exr`` -> ``anim_0007.exr`` for frame 7 (four digits, more when needed)."""
    path = Path(path)
    return path.with_name(f"{path.stem}_{frame:04d}{path.suffix}")


def reference_path(pattern: str, frame: int) -> Path:
    """The reference image of ``frame``: ``pattern`` formatted with ``frame`` when it holds a
    ``{frame}`` field (``ref_{frame:04d}.exr``), else numbered like the outputs.

    Raises
    ------
    InputError
        When the pattern is not a valid format string with only a ``frame`` field.
    """
    if "{" not in pattern:
        return frame_path(pattern, frame)
    try:
        return Path(pattern.format(frame=frame))
    except (KeyError, IndexError, ValueError) as exc:
        raise InputError(pattern, f"--reference: not a pattern with a {{frame}} field such as "
                                  f"ref_{{frame:04d}}.exr ({type(exc).__name__}: {exc})") from None


def frame_settings(settings: RenderSettings, frame: int) -> RenderSettings:
    """``settings`` with the seed of ``frame`` (``frame_seed(settings.seed, frame)``)."""
    return replace(settings, seed=frame_seed(settings.seed, frame))


@dataclass
class FrameOutputs:
    """The files of an animation, by frame, as checked before rendering."""

    image: str
    png: str | None
    report: str | None
    #: how many of these files existed before the run (replaced, and said so)
    replaced: int = 0

    def of(self, frame: int) -> list[Path]:
        """The files of ``frame``: image, then the PNG and the report where asked for."""
        return [frame_path(p, frame) for p in (self.image, self.png, self.report)
                if p is not None]


def check_frame_outputs(image: str, png: str | None, report: str | None,
                        frames: list[int]) -> FrameOutputs:
    """Check, before any work, every file every frame will write and the summary report.

    Raises
    ------
    InputError
        Naming the path and the problem (format, folder in the way, permission, two outputs
        on one path).
    """
    seen: dict[Path, str] = {}
    if report is not None:
        check_output_paths(image, png, report)  # the summary's own path
        seen[Path(report).resolve()] = "the summary report"
    replaced = int(report is not None and Path(report).exists())
    for frame in frames:
        paths = check_output_paths(str(frame_path(image, frame)),
                                   None if png is None else str(frame_path(png, frame)),
                                   None if report is None else str(frame_path(report, frame)))
        for path in paths:
            other = seen.setdefault(path.resolve(), f"frame {frame}")
            if other != f"frame {frame}":
                raise InputError(path, f"frame {frame} would overwrite a file of {other}")
            replaced += path.exists()
    return FrameOutputs(image, png, report, replaced)


def resolve_frames(config: SceneConfig, frames: list[int], lo: np.ndarray, hi: np.ndarray,
                   width: int, height: int) -> dict[int, SceneConfig]:
    """Every frame's static config, each camera checked, before the first frame renders.

    Raises
    ------
    InputError
        Naming the scene file and the frame whose camera or lights are degenerate.
    """
    resolved = {}
    for frame in frames:
        try:
            resolved[frame] = config.at_frame(frame, lo, hi, width, height)
            resolved[frame].resolve_camera(lo, hi, width, height)
        except InputError as exc:
            raise InputError(exc.path, f"frame {frame}: {exc.problem}") from None
    return resolved


def render_frames(frames: list[int], configs: dict[int, SceneConfig], settings: RenderSettings,
                  render_one: RenderOne, on_frame: Callable[[int, RenderResult], None],
                  render_many: RenderMany | None = None,
                  progression_of: Callable[[int], Progression] | None = None) -> None:
    """Render ``frames`` in order, handing each result to ``on_frame(frame, result)``.

    Parameters
    ----------
    frames : frame numbers.
    configs : each frame's resolved config (``resolve_frames``).
    settings : the run's settings; frame f renders with ``frame_seed(settings.seed, f)``.
    render_one : renders one frame from its config and settings (the single-process
        schedulers).
    render_many : where given, renders every frame in one job instead (the distributed runtime:
        its nodes resolve each frame's config and seed, and keep their caches and statistics
        from frame to frame) and calls ``on_frame`` itself.
    progression_of : ``progression_of(frame)``, the passes and stopping rules of each frame
        (``render.progressive``); None: each frame in one pass.
    """
    if progression_of is None:
        def progression_of(frame):
            return None
    if render_many is not None:
        render_many(list(frames), on_frame, progression_of)
        return
    for frame in frames:
        on_frame(frame, render_one(configs[frame], frame_settings(settings, frame),
                                   progression=progression_of(frame)))


@dataclass
class _Summary:
    """What the summary report and the last line gather, frame by frame."""

    entries: list[dict] = field(default_factory=list)

    def add(self, frame: int, seed: int, files: list[Path], result: RenderResult,
            error: dict | None, reference: Path | None) -> dict:
        entry = {"frame": frame, "seed": seed, "files": [str(p) for p in files],
                 "seconds": result.seconds, "loads": int(result.counters.get("loads", 0))}
        if error is not None:
            entry["error"] = dict(error, reference=str(reference))
        if result.progress is not None:  # the frame's passes: its error against time
            entry["stopped_by"] = result.progress["stopped_by"]
            entry["passes"] = result.progress["passes"]
        self.entries.append(entry)
        return entry

    def totals(self, wall: float) -> tuple[dict, dict]:
        seconds = [float(e["seconds"].get("total", 0.0)) for e in self.entries]
        loads = [e["loads"] for e in self.entries]
        totals = {"frames": len(self.entries), "seconds": round(sum(seconds), 4),
                  "wall_seconds": round(wall, 4), "loads": int(sum(loads))}
        means = {"seconds_per_frame": round(sum(seconds) / max(len(seconds), 1), 4),
                 "loads_per_frame": sum(loads) / max(len(loads), 1)}
        errors = [e["error"] for e in self.entries if "error" in e]
        if errors:
            means["mse"] = float(np.mean([e["mse"] for e in errors]))
            means["psnr_db"] = float(np.mean([np.inf if e["psnr_db"] is None else e["psnr_db"]
                                              for e in errors]))
            rel = [e["rel_mse"] for e in errors]
            means["rel_mse"] = None if None in rel else float(np.mean(rel))
        return totals, means


def run_animation(args, *, store_path: str, config: SceneConfig, settings: RenderSettings,
                  bounds: tuple[np.ndarray, np.ndarray], scheduler: str, options: dict,
                  outputs: FrameOutputs, render_one: RenderOne,
                  render_many: RenderMany | None = None, legend=None,
                  rules: StopRules | None = None) -> int:
    """``vastray render --frames N``: render, write and report every frame, then the summary.

    ``args`` are the parsed ``render`` options (``frames``, ``first_frame``, ``reference``,
    ``exposure``, ``quiet``, size and sampling); ``outputs`` come from
    ``check_frame_outputs``, made before the store was opened; ``rules`` say when each
    frame's passes stop (default: at ``settings.spp``).
    """
    first = args.first_frame or 0
    frames = list(range(first, first + (args.frames or 1)))
    lo, hi = bounds
    configs = resolve_frames(config, frames, lo, hi, settings.width, settings.height)
    references = _check_references(args.reference, frames, settings) if args.reference else {}
    summary = _Summary()
    start = time.perf_counter()
    recoveries: list[dict] = []  # nodes lost so far (each frame's result lists them all)
    loaded: dict[int, np.ndarray] = {}  # a frame's reference, read once for passes and error

    def reference_image(frame: int) -> np.ndarray:
        if frame not in loaded:
            loaded[frame] = read_image(references[frame])
        return loaded[frame]

    # every frame's files, or none: renamed into place together (a frame that cannot be
    # written sends the frames so far to a rescue folder, vastray.outputs)
    with StagedOutputs() as written:
        def on_frame(frame: int, result: RenderResult) -> None:
            files = outputs.of(frame)
            image = result.film.image()
            count_overflow(image, result.counters, str(files[0]))
            reference = references.get(frame)
            error = image_error(image, reference_image(frame)) if reference else None
            loaded.pop(frame, None)
            seed = frame_seed(settings.seed, frame)
            depth, normal = result.film.depth_image(), result.film.normal_image()
            writers = {files[0]: lambda path: write_image(path, image, depth, normal,
                                                          args.exposure, legend=legend)}
            if outputs.png is not None:
                writers[files[1]] = lambda path: write_png(path, image, args.exposure,
                                                           legend=legend)
            if outputs.report is not None:
                report = build_report(
                    store=store_path, settings=dict(asdict(settings), seed=seed),
                    seconds=result.seconds, counters=result.counters, error=error,
                    reference=None if reference is None else str(reference),
                    scheduler=scheduler, options=options, frame=frame,
                    progress=result.progress)
                writers[files[-1]] = lambda path: write_report(path, report)
            written.add(writers)
            entry = summary.add(frame, seed, files, result, error, reference)
            recoveries[:] = result.counters.get("recoveries", recoveries)
            if not args.quiet:
                print(_frame_line(entry, len(summary.entries), len(frames)), file=sys.stderr)

        def progression_of(frame: int) -> Progression:
            reference = references.get(frame)
            return Progression(settings.width, settings.height,
                               rules or StopRules(settings.spp),
                               None if reference is None else reference_image(frame))

        try:
            render_frames(frames, configs, settings, render_one, on_frame, render_many,
                          progression_of)
        except KeyboardInterrupt as stop:  # Ctrl-C or SIGTERM: the frames done are kept
            stop.kept = _keep_frames_done(written, summary.entries, outputs, len(frames))
            raise
        done = {e["frame"] for e in summary.entries}
        if done != set(frames):
            raise RuntimeError(f"the renderer returned frames {sorted(done)}, not {frames}")
        totals, means = summary.totals(time.perf_counter() - start)
        if outputs.report is not None:
            report = run_header(store_path, scheduler, options)
            report.update(
                settings=asdict(settings),
                animation={"first_frame": first, "frames": len(frames), "seed": settings.seed},
                frames=summary.entries, totals=totals, means=means)
            if references:
                report["error_vs_time"] = [{"frame": e["frame"],
                                            "seconds": e["seconds"].get("total"), **e["error"]}
                                           for e in summary.entries]
            written.add({Path(outputs.report): lambda path: write_report(path, report)})
    if not args.quiet:
        print(_summary_line(args, outputs, frames, totals, means), file=sys.stderr)
        for line in recovery_lines({"recoveries": recoveries}):
            print(line, file=sys.stderr)
    return 0


def _keep_frames_done(written: StagedOutputs, entries: list[dict], outputs: FrameOutputs,
                      count: int) -> str:
    """Rename the staged files of the frames finished (``entries``) into place, each frame's
    together, before an interruption removes the rest; what was kept, for the last line."""
    done = []
    for entry in entries:
        try:
            for path in entry["files"]:
                tmp = written.staged[Path(path)]
                publish_mode(tmp)
                os.replace(tmp, path)
        except (KeyError, OSError) as exc:
            log.warning("frame %d could not be kept: %s", entry["frame"], exc)
            continue
        done.append(entry["frame"])
    if not done:
        return "no frame finished, none written"
    files = [_pattern(p, done) for p in (outputs.image, outputs.png, outputs.report)
             if p is not None]
    return (f"{len(done)} of {count} frame{'s' * (count > 1)} written: {', '.join(files)}")


def _check_references(pattern: str, frames: list[int], settings: RenderSettings
                      ) -> dict[int, Path]:
    """Each frame's reference image, each read once now so a missing or misfit one fails
    before the first frame renders (they are read again, one at a time, as frames finish)."""
    references = {}
    for frame in frames:
        path = reference_path(pattern, frame)
        shape = read_image(path).shape
        if shape != (settings.height, settings.width, 3):
            raise InputError(path, f"reference of frame {frame} is {shape[1]}x{shape[0]}, the "
                                   f"render is {settings.width}x{settings.height}")
        references[frame] = path
    return references


def _frame_line(entry: dict, done: int, count: int) -> str:
    """One progress line per finished frame."""
    line = (f"frame {entry['frame']} ({done}/{count}): {entry['seconds'].get('total', 0):.2f} s, "
            f"{entry['loads']} domain loads")
    if "error" in entry:
        error = entry["error"]
        psnr = "inf" if error["psnr_db"] is None else f"{error['psnr_db']:.2f}"
        line += f", MSE {error['mse']:.4g}, PSNR {psnr} dB"
    return line


def _pattern(path: str, frames: list[int]) -> str:
    """The files of ``path`` over ``frames`` as a shell brace pattern: ``a_{0000..0009}.exr``
    (frames not in one run: ``a_{0000,0002}.exr``)."""
    if len(frames) == 1:
        return str(frame_path(path, frames[0]))
    path = Path(path)
    if list(frames) == list(range(frames[0], frames[-1] + 1)):
        numbers = f"{frames[0]:04d}..{frames[-1]:04d}"
    else:
        numbers = ",".join(f"{f:04d}" for f in frames)
    return str(path.with_name(f"{path.stem}_{{{numbers}}}{path.suffix}"))


def _summary_line(args, outputs: FrameOutputs, frames: list[int], totals: dict,
                  means: dict) -> str:
    """The last line of an animation: the files, the work, the time per frame and the error."""
    files = [_pattern(p, frames) for p in (outputs.image, outputs.png, outputs.report)
             if p is not None]
    if outputs.report is not None:
        files.append(f"summary {outputs.report}")
    line = (f"wrote {len(frames)} frame{'s' if len(frames) > 1 else ''}: {', '.join(files)} "
            f"({args.width}x{args.height}, {args.spp} spp, {args.integrator}) in "
            f"{totals['wall_seconds']:.2f} s, {means['seconds_per_frame']:.2f} s per frame, "
            f"{totals['loads']} domain loads")
    if "mse" in means:
        psnr = means["psnr_db"]
        psnr = "inf" if not np.isfinite(psnr) else f"{psnr:.2f}"
        line += f", mean MSE {means['mse']:.4g}, mean PSNR {psnr} dB"
    if outputs.replaced:
        line += f"; replaced {outputs.replaced} existing file{'s' * (outputs.replaced > 1)}"
    return line
