"""``canergy keys``: a master key for the supervisor, node keys derived from it for the nodes."""

from __future__ import annotations

import argparse
from pathlib import Path

from canergy.argtypes import bounded_int, node_ids
from canergy.auth.keys import EPOCH_MAX, load_key, new_master, node_key_of, write_key
from canergy.cli.summaries import SUMMARIES


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "keys",
        help=SUMMARIES["keys"],
        description="Without --master: create a random master key (the supervisor's --auth). "
        "With --master and --nodes: derive node keys from it (each node's --auth: a node holds "
        "only its own). Files are created with mode 0600 and never replaced; keys are never "
        "printed.",
    )
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        help="the key file to create; for node keys a directory (node-NNN.key inside, created "
        "if missing), or a .key file for a single node",
    )
    p.add_argument(
        "--epoch",
        type=bounded_int(0, EPOCH_MAX),
        help="a master key's provisioning epoch: a new one for every supervisor whose books "
        "start again (default 1). Node keys take their master's epoch: with --master, --epoch "
        "only states the epoch expected of it, and another is refused",
    )
    p.add_argument("--master", type=Path, help="derive node keys from this master key file")
    p.add_argument("--nodes", type=node_ids, help="the nodes to derive keys for, e.g. 1-5,9")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.master is None:
        if args.nodes is not None:
            raise ValueError("--nodes derives node keys: give the --master key to derive from")
        epoch = 1 if args.epoch is None else args.epoch
        write_key(args.output, new_master(epoch))
        print(f"canergy keys: wrote a master key (epoch {epoch}) to {args.output}")
        return 0
    if args.nodes is None:
        raise ValueError("--master derives node keys: say which with --nodes")
    master = load_key(args.master)
    if master.kind != "master":
        raise ValueError(f"--master {args.master}: a {master.kind} key, not a master key")
    if args.epoch is not None and args.epoch != master.epoch:
        raise ValueError(
            f"--epoch {args.epoch}: node keys take the epoch of their master key, and "
            f"{args.master} is epoch {master.epoch} (a new epoch needs a new master key: "
            f"canergy keys -o NEW.key --epoch {args.epoch})"
        )
    nodes: tuple[int, ...] = args.nodes
    if len(nodes) == 1 and args.output.suffix == ".key":
        targets = {nodes[0]: args.output}
    else:
        args.output.mkdir(mode=0o700, parents=True, exist_ok=True)
        targets = {n: args.output / f"node-{n:03d}.key" for n in nodes}
    for path in targets.values():
        if path.exists():
            raise ValueError(f"{path} exists: key files are never replaced")
    for node, path in targets.items():
        write_key(path, node_key_of(master, node))
    print(f"canergy keys: wrote {len(targets)} node key(s), epoch {master.epoch}")
    return 0
