"""``vastray launch``: a render with its nodes started on SSH hosts."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vastray.actors.launch import DEFAULT_SSH
from vastray.commands_render import add_render_arguments
from vastray.execute import run
from vastray.request import DEFAULT_NODE_TIMEOUT_S, RenderRequest, positive_int
from vastray.scene.errors import InputError
from vastray.transport.keys import (
    load_node_keys,
    node_bundle,
)

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


def register(sub: argparse._SubParsersAction) -> None:
    launch = sub.add_parser(
        "launch", help="render with nodes started on SSH hosts",
        description=LAUNCH_DESCRIPTION, epilog=LAUNCH_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    launch.add_argument("--hosts", required=True, metavar="HOSTFILE",
                        help="one node per line: HOST [python=PATH] [slots=N]")
    launch.add_argument("--advertise", help="address the hosts reach this machine at "
                                            "(default: its fully qualified host name)")
    launch.add_argument("--port", type=positive_int, help="coordinator port (default: a free one)")
    launch.add_argument("--ssh", default=DEFAULT_SSH,
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
    # checked before any node starts: the render of len(hosts) nodes that join on --port
    request = RenderRequest.from_namespace(args, nodes=len(hosts), listen=f"0.0.0.0:{port}")
    started = start_nodes(hosts, coordinator, bundles, Path(args.logs),
                          ssh=args.ssh, timeout=args.node_timeout or DEFAULT_NODE_TIMEOUT_S)
    if not args.quiet:
        print(f"{len(hosts)} node(s) started; their logs are in {args.logs}", file=sys.stderr)
    try:
        return run(request, launched=started)
    finally:
        stop_nodes(started)


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("", 0))
        return probe.getsockname()[1]
