"""The ``vastray`` command line: one sub-command per area, each with a runnable example.

Configuration lives here only; library modules log through ``logging.getLogger(__name__)``.
"""

# The imports below come after SIGUSR1 is ignored, on purpose:
# ruff: noqa: E402
from __future__ import annotations

import signal
import threading

if threading.current_thread() is threading.main_thread():
    # SIGUSR1 asks a render for a checkpoint (``vastray.checkpoint``); its default action
    # kills the process, so it is ignored first thing, before any other module loads: one
    # sent in a render's first moments, before the checkpoints' handler takes over, must
    # change nothing (the console script imports this module first).
    signal.signal(signal.SIGUSR1, signal.SIG_IGN)

import argparse
import difflib
import logging
import os
import select
import sys

from vastray.actors.node_failure import NodeFailure
from vastray.processes import Terminated, raise_terminated
from vastray.scene.errors import InputError

DESCRIPTION = """\
vastray renders triangle data too large for one machine's memory, split into spatial domains,
with ambient occlusion or path tracing, out-of-core on one node or across a cluster.

typical use (every line runs on a fresh install):
  vastray render -o default.exr --png default.png          # built-in scene, one command
  vastray generate rm -o rm.store --resolution 256 --grid 4x4x4   # a procedural scene
  vastray info rm.store
  vastray verify rm.store                                  # checksums, counts, indices
  vastray render rm.store -o rm.exr --integrator pt --spp 16 --cache 25%
  vastray data fetch -o samples                            # real scans, checksummed
  vastray partition samples/stanford_bunny.ply -o bunny.store --grid 2x2x2
  vastray render bunny.store -o bunny.exr --png bunny.png
  vastray render rm.store -o rm-ooc.exr --spp 16 --cache 25% --scheduler spec-ooc
  vastray compare rm-ooc.exr rm.exr                        # MSE, PSNR: the same image
  vastray render rm.store -o orbit.exr --scene orbit.toml --frames 36   # an animation
  vastray plot a.json b.json -o error_vs_time.png          # error vs time of several runs
"""


#: Options users reach for that vastray spells differently: the option the command has
#: instead, and the hint shown when one is given.
OPTION_HINTS = {
    "--resolution": ("--width", "the image size is --width W --height H"),
    "--size": ("--width", "the image size is --width W --height H"),
    "--samples": ("--spp", "samples per pixel are --spp N"),
}


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are two lines: the problem, then where help is (not
    the whole usage block), and whose sub-commands name an unknown option themselves, with
    the closest option they have."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n"
                     f"(`{self.prog} --help` lists the options)\n")

    def parse_known_args(self, args=None, namespace=None):
        parsed, extras = super().parse_known_args(args, namespace)
        if extras and self._subparsers is None:  # a command's own parser, not the top one
            self.error(f"unrecognized arguments: {' '.join(extras)}{self._hint(extras)}")
        return parsed, extras

    def _hint(self, extras: list[str]) -> str:
        """'; did you mean --x?' for the first unknown option, from ``OPTION_HINTS`` or the
        closest option of this command; else ''."""
        unknown = next((e.split("=")[0] for e in extras if e.startswith("--")), None)
        if unknown is None:
            return ""
        instead, hint = OPTION_HINTS.get(unknown, (None, ""))
        if instead in self._option_string_actions:
            return f" ({hint})"
        close = difflib.get_close_matches(unknown, list(self._option_string_actions), n=1)
        return f" (did you mean {close[0]}?)" if close else ""


def build_parser() -> argparse.ArgumentParser:
    from vastray import (
        commands_compare,
        commands_data,
        commands_keys,
        commands_launch,
        commands_render,
        commands_scene,
        commands_sim,
        plot,
    )

    parser = Parser(
        prog="vastray", description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-vv for debug)")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    parser.subcommands = sub
    commands_scene.register(sub)
    commands_render.register(sub)
    commands_launch.register(sub)
    commands_keys.register(sub)
    commands_compare.register(sub)
    commands_data.register(sub)
    plot.register(sub)
    commands_sim.register(sub)
    node = sub.add_parser("node", help="run one render node (started by a coordinator)",
                          add_help=False)
    node.set_defaults(func=None)
    return parser


def _version() -> str:
    from vastray.report import package_version

    return package_version()


class KeptStream:
    """A text stream (stderr) whose writes never fail on a reader that has gone: from the
    first ``BrokenPipeError`` on, what is written is dropped (its descriptor then points to
    the null device, for the interpreter's exit and any child process) and ``broken`` is
    True. Everything else is the stream's own."""

    def __init__(self, stream):
        self._stream = stream
        self.broken = False

    def write(self, text: str) -> int:
        if not self.broken:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._drop()
        return len(text)

    def flush(self) -> None:
        if not self.broken:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._drop()

    def _drop(self) -> None:
        self.broken = True
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self._stream.fileno())
            os.close(devnull)
        except (AttributeError, OSError, ValueError):
            pass

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, raise_terminated)
        # SIGUSR1 is ignored since this module's import (above). SIGPIPE stays ignored
        # (Python's default), so a closed pipe is a BrokenPipeError that ``_closed_output``
        # below tells apart, rather than SIG_DFL's silent death at any write to any pipe or
        # socket: a render would die without a word, its nodes left running and its
        # checkpoint unwritten, if a node's pipe broke.
    verbose, rest = _leading_verbosity(argv)
    if rest[:1] == ["node"]:  # `vastray -v node ...`: the node parses its own options
        from vastray.actors.node import main as node_main

        return node_main(rest[1:], verbose=verbose)
    parser = build_parser()
    resumed = None
    if rest[:1] == ["render"]:
        try:
            resumed = _resumed_command(parser.subcommands.choices["render"], rest[1:])
        except InputError as exc:
            _say(f"vastray render: error: {exc}")
            return 2
        if resumed is not None:  # the interrupted run's command, then what was typed now
            rest = ["render", *resumed[1], *rest[1:]]
            argv = [*argv[:len(argv) - len(rest) + len(resumed[1])], *rest]
    args = parser.parse_args(argv)  # --help and --version: argparse ignores a closed stdout
    if args.command == "render":
        args.argv = rest[1:]  # kept in its checkpoints, for a resume without retyping
        if resumed is not None and not args.quiet:
            import shlex

            print(f"resuming {resumed[0]}: vastray render {shlex.join(resumed[1])}",
                  file=sys.stderr)
    # Progress bars, log lines and summaries go to stderr: one whose reader has gone
    # (`2>&1 | head -1`, a closed terminal) must never cost the result, so they are dropped
    # from then on and the command goes on to write its outputs.
    stderr = sys.stderr = KeptStream(sys.stderr)
    logging.basicConfig(
        level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        status = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe fails here, not in the interpreter's exit
        return 141 if status == 0 and stderr.broken else status
    except BrokenPipeError:  # `vastray info STORE | head`: the reader has all it wanted
        if not _closed_output():
            raise  # a pipe of the command's own broke: a failure, not the reader leaving
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # so the exit's flush of stdout fails silently
        return 141  # 128 + SIGPIPE, what a shell reports for a command its pipe closed
    except InputError as exc:
        _say(f"vastray {args.command}: error: {exc}")
        return 2
    except NodeFailure as exc:
        _say(f"vastray {args.command}: error: {exc}")
        return 3
    except MemoryError:
        _say(f"vastray {args.command}: error: out of memory; lower --width/--height, "
             "--batch-size or --max-samples-in-flight")
        return 2
    except Terminated as exc:
        _quiet_abandoned_tasks()
        kept = getattr(exc, "kept", None) or (  # an animation's frames done, or the passes
            "the passes done kept" if getattr(exc, "checkpointed", False)
            else "no output written")
        stopped = "nodes stopped, " if args.command in ("render", "launch") else ""
        _say(f"vastray {args.command}: terminated; {stopped}{kept}")
        return 143
    except KeyboardInterrupt as exc:
        _quiet_abandoned_tasks()
        kept = getattr(exc, "kept", None)
        _say(f"vastray {args.command}: interrupted" + (f"; {kept}" if kept else ""))
        return 130


def _resumed_command(render: argparse.ArgumentParser, typed: list[str]
                     ) -> tuple[str, list[str]] | None:
    """For ``vastray render --resume CHECKPOINT`` typed without a STORE: (the checkpoint, the
    command of the run that wrote it, as kept in it), so that what was typed now applies on
    top of that command (``--spp 4096`` goes further) and nothing needs retyping. None
    otherwise: no ``--resume``, a STORE typed (then the options typed are the render's), or
    a checkpoint without a command (an older one, or not a sound one, which the render then
    names)."""
    takes = {option: action.nargs for action in render._actions
             for option in action.option_strings}
    checkpoint, i = None, 0
    while i < len(typed):
        token = typed[i]
        option, eq, value = token.partition("=")
        if token == "--":
            return None  # a STORE follows
        if token.startswith("-") and option in takes:
            nargs = takes[option]
            count = 0 if eq else (1 if nargs is None else nargs if isinstance(nargs, int)
                                  else int(nargs == "?" and i + 1 < len(typed)
                                           and not typed[i + 1].startswith("-")))
            if option == "--resume":
                checkpoint = value if eq else (typed[i + 1] if i + 1 < len(typed) else None)
            i += 1 + count
            continue
        if not token.startswith("-"):
            return None  # a STORE
        i += 1  # an unknown option: argparse names it
    if checkpoint is None:
        return None
    from vastray.checkpoint import checkpoint_command, why_no_command

    command = checkpoint_command(checkpoint)
    if command is None and not any(t in ("-o", "--output") or t.startswith("--output=")
                                   for t in typed):
        raise InputError(checkpoint, why_no_command(checkpoint))  # else argparse's "-o required"
    return None if command is None else (checkpoint, command)


def _leading_verbosity(argv: list[str]) -> tuple[int, list[str]]:
    """The verbosity of the global flags before the sub-command (``-v``, ``-vv``,
    ``--verbose``) and the arguments after them."""
    verbose = 0
    for index, arg in enumerate(argv):
        if arg == "--verbose":
            verbose += 1
        elif len(arg) > 1 and arg.strip("v") == "-":
            verbose += len(arg) - 1
        else:
            return verbose, argv[index:]
    return verbose, []


def _quiet_abandoned_tasks() -> None:
    """After Ctrl-C or SIGTERM, asyncio's own log of the tasks the stop abandoned ("Task
    exception was never retrieved", "Task was destroyed but it is pending!", "coroutine ...
    was never awaited": dozens of lines from ``vastray simulate``'s virtual nodes) is not
    shown: the one line said is the news."""
    logging.getLogger("asyncio").setLevel(logging.CRITICAL + 1)
    import warnings

    warnings.filterwarnings("ignore", message="coroutine .* was never awaited",
                            category=RuntimeWarning)


def _say(line: str) -> None:
    """``line`` on stderr, unless stderr is gone (`2>&1 | head`): the exit status says it."""
    try:
        print(line, file=sys.stderr)
    except OSError:
        pass


def _closed_output() -> bool:
    """Whether stdout or stderr is a pipe (or socket) whose reader has gone: what a
    BrokenPipeError from ``head`` closing its end means. True where that cannot be asked
    (no ``select.poll``), as the likely cause."""
    if not hasattr(select, "poll"):
        return True
    for stream in (sys.stdout, sys.stderr):
        try:
            fd = stream.fileno()
        except (AttributeError, OSError, ValueError):  # replaced, or closed by the command
            continue
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        if any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0)):
            return True
    return False


if __name__ == "__main__":
    sys.exit(main())
