"""``vastray keys``: the coordinator's and the nodes' key pairs."""

from __future__ import annotations

import argparse
from pathlib import Path

from vastray.scene.errors import InputError
from vastray.transport.keys import (
    COORDINATOR_KEY,
    NODES_DIR,
    add_node_key,
    check_node_name,
    generate_keys,
    load_coordinator_keys,
    load_node_keys,
    write_bundle,
)


def register(sub: argparse._SubParsersAction) -> None:
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


def run_keys(args: argparse.Namespace) -> int:
    # every name checked before anything is written (a bad one once left a folder with a
    # coordinator key, a repeated one a node on the allow-list without its bundle)
    for name in args.node:
        check_node_name(name)
    repeated = sorted({name for name in args.node if args.node.count(name) > 1})
    if repeated:
        raise InputError(None, f"--node {repeated[0]} is given twice; name each node once")
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
