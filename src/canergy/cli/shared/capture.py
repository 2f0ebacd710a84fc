"""Flags and output shared by ``dump``, ``decode`` and ``audit``: MAC checks, the view,
reading captures."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any, TextIO

import can

from canergy.argtypes import argument, node_ids, odrive_ids
from canergy.auth.capture import CaptureAuth
from canergy.auth.keys import load_key
from canergy.cli.shared.mit import add_model_flag, models_of
from canergy.codec import Codec
from canergy.inspect.audit import Auditor
from canergy.inspect.captures import read_file, read_text
from canergy.inspect.frames import Described
from canergy.inspect.others import Dbc, Namer
from canergy.inspect.render import Stamps, line


def auth_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--auth",
        type=Path,
        metavar="KEYFILE",
        help="check the MACs of authenticated frames with this key (the master key, or a "
        "node's own key for its frames): mac ok / MAC BAD; without it they show mac ?",
    )


def capture_auth(args: argparse.Namespace, codec: Codec) -> CaptureAuth:
    return CaptureAuth(codec, load_key(args.auth) if args.auth is not None else None)


def view_flags(p: argparse.ArgumentParser) -> None:
    auth_flag(p)
    p.add_argument(
        "--audit",
        action="store_true",
        help="run the audit alongside: a frame it flags (a forgery, a second supervisor's "
        "interleaved sequence...) gets a line starting with !! under it",
    )
    p.add_argument("--nodes", type=node_ids, help="only frames of these node ids, e.g. 1-5,9")
    p.add_argument("--hide-foreign", action="store_true", help="hide frames that are not canergy's")
    others_flags(p)
    p.add_argument("--json", action="store_true", help="one JSON object per frame")
    p.add_argument(
        "--color",
        choices=["auto", "always", "never"],
        default="auto",
        help="colour per transaction (auto: only on a terminal)",
    )


def others_flags(p: argparse.ArgumentParser) -> None:
    """``--dbc``, ``--odrive-names``, ``--mit-names``, ``--moteus-names``, ``--no-canopen``: how
    frames of other protocols are named (``canergy.inspect.others``)."""
    others = p.add_argument_group(
        "other protocols",
        "frames that are not canergy's are named by a DBC that defines their identifier, then "
        "as ODrive CAN Simple for --odrive-names, MIT mode for --mit-names, moteus for "
        "--moteus-names, then by CANopen's predefined connection set; a frame of theirs whose "
        "data does not decode is named with the reason and counted as undecodable",
    )
    others.add_argument(
        "--dbc",
        action="append",
        type=lambda text: argument(Dbc.load, text),
        default=[],
        metavar="FILE",
        help="name and decode the frames this DBC defines (cantools; repeatable), e.g. the "
        "ODrive DBC odrive-can installs",
    )
    others.add_argument(
        "--odrive-names",
        type=odrive_ids,
        metavar="IDS",
        help="name 11-bit frames of these ODrive node ids (0-63) as CAN Simple commands",
    )
    others.add_argument(
        "--mit-names",
        type=node_ids,
        metavar="IDS",
        help="name 11-bit frames to these MIT-mode motor ids (1-127) as commands (p, v, kp, kd, "
        "t_ff in units) or enter/exit/zero/clear, and their replies (position, velocity, "
        "torque) on the model's reply id (CubeMars 0, Damiao id+0x10); give --mit-model",
    )
    add_model_flag(others, "the --mit-names motors' model (its ranges)")
    others.add_argument(
        "--moteus-names",
        type=node_ids,
        metavar="IDS",
        help="name frames from and to these moteus controller ids (1-127): registers written, "
        "read and replied with their names and values, errors, diagnostic stream text",
    )
    others.add_argument(
        "--no-canopen", action="store_true", help="do not name 11-bit frames as CANopen's"
    )


def namer_of(args: argparse.Namespace) -> Namer:
    """``ValueError``: --mit-names without --mit-model, or a motor id --mit-model names
    that --mit-names does not (or leaves without a model)."""
    mit, spec = args.mit_names or (), args.mit_model
    if mit and spec is None:
        raise ValueError("--mit-names needs --mit-model (the motors' ranges)")
    return Namer(
        args.dbc,
        odrive_nodes=args.odrive_names or (),
        moteus_nodes=args.moteus_names or (),
        mit_models={} if spec is None else models_of(spec, mit, "--mit-names"),
        canopen_names=not args.no_canopen,
    )


def garbage(number: int, text: str, reason: str) -> None:
    print(f"line {number}: skipped ({reason}): {text[:80]}", file=sys.stderr)


def capture_frames(path: str) -> Iterator[can.Message]:
    if path == "-":
        return read_text(sys.stdin, garbage)
    return read_file(Path(path), garbage)


def show(
    described: Iterable[Described],
    args: argparse.Namespace,
    out: TextIO,
    live: bool = False,
    stamps: Stamps | None = None,
) -> None:
    """The frames as lines (or JSON objects), those --nodes/--hide-foreign leave; ``stamps``:
    candump's ``-t`` timestamps instead of the absolute ones, counted over the frames shown."""
    colour = args.color == "always" or (args.color == "auto" and out.isatty())
    auditor = Auditor() if args.audit else None
    namer = namer_of(args)
    for d in described:
        if not d.ours and not d.error_frame:
            d = replace(d, other=namer.named(d))
        flagged = audited(auditor, d)
        if args.hide_foreign and d.message is None and not d.ours:
            continue
        if args.nodes is not None and (d.message is None or d.message.node not in args.nodes):
            continue
        if args.json:
            out.write(json.dumps(d.as_json()) + "\n")
        else:
            stamp = stamps.text(d.timestamp) if stamps is not None else None
            out.write(line(d, colour=colour, stamp=stamp) + "\n")
        for here, v in flagged:
            assert auditor is not None
            many = auditor.channels
            where = f"{here}{v.channel}/{v.node}: " if many and v.node is not None else here
            out.write(
                json.dumps({"violation": v.as_json(many)}) if args.json else f"!! {where}{v.what}"
            )
            out.write("\n")
        if live:
            out.flush()


def audited(auditor: Auditor | None, d: Described) -> list[tuple[str, Any]]:
    """The audit's new violations once ``d`` is fed, each with where it points ("" for this
    frame; some are decided later and concern an earlier one). A MAC that failed moves nothing."""
    if auditor is None:
        return []
    before = len(auditor.violations)
    auditor.feed(replace(d, message=None, crc_ok=None) if d.mac == "BAD" else d)
    return [
        ("" if v.frame == auditor.frames else f"frame {v.frame}: ", v)
        for v in auditor.violations[before:]
    ]
