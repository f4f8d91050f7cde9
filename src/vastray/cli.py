"""The ``vastray`` command line: one sub-command per area, each with a runnable example.

Configuration lives here only; library modules log through ``logging.getLogger(__name__)``.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

from vastray.actors.coordinator import NodeFailure
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
  vastray compare rm.exr reference.exr
  vastray render rm.store -o orbit.exr --scene orbit.toml --frames 36   # an animation
  vastray plot a.json b.json -o error_vs_time.png          # error vs time of several runs
"""


def build_parser() -> argparse.ArgumentParser:
    from vastray import commands_data, commands_render, commands_scene, plot

    parser = argparse.ArgumentParser(
        prog="vastray", description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-vv for debug)")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    commands_scene.register(sub)
    commands_render.register(sub)
    commands_data.register(sub)
    plot.register(sub)
    node = sub.add_parser("node", help="run one render node (started by a coordinator)",
                          add_help=False)
    node.set_defaults(func=None)
    return parser


def _version() -> str:
    from vastray.report import package_version

    return package_version()


class Terminated(KeyboardInterrupt):
    """SIGTERM (``timeout``, Slurm, systemd): cleaned up exactly like Ctrl-C."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_terminated)
    if argv[:1] == ["node"]:
        from vastray.actors.node import main as node_main

        return node_main(argv[1:])
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"vastray {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except NodeFailure as exc:
        print(f"vastray {args.command}: error: {exc}", file=sys.stderr)
        return 3
    except MemoryError:
        print(f"vastray {args.command}: error: out of memory; lower --width/--height, "
              "--batch-size or --max-samples-in-flight", file=sys.stderr)
        return 2
    except Terminated:
        print(f"vastray {args.command}: terminated; nodes stopped, no output written",
              file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print(f"vastray {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
