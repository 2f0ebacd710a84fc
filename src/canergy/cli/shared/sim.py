"""Flags shared by ``simulate`` and ``sweep``: strategies, the channel model, the run's
length and output."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from canergy.argtypes import (
    add_duration,
    bounded_int,
    duration_or_zero,
    energy,
    milliseconds,
    probability,
)
from canergy.sim.channel import PRESETS, channel
from canergy.sim.engine import STRATEGIES, SimConfig
from canergy.units import UJ_PER_J, US_PER_S

ALL = list(STRATEGIES)


LOSS_POINTS_MAX = 100
"""Most loss rates in one sweep."""


def strategies(text: str) -> list[str]:
    names = ALL if text == "all" else [s.strip() for s in text.split(",")]
    unknown = [n for n in names if n not in STRATEGIES]
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown strategy {unknown[0][:24]!r} (all, {', '.join(ALL)})"
        )
    return names


def loss_rates(text: str) -> list[float]:
    parts = text.split(",")
    if len(parts) > LOSS_POINTS_MAX:
        raise argparse.ArgumentTypeError(f"{len(parts)} rates, at most {LOSS_POINTS_MAX}")
    return [probability(part) for part in parts]


def check_out_dir(out: Path, option: str = "--out") -> None:
    """Fail now, not after the runs, unless ``out`` is a directory or can be made one: the
    nearest existing folder on its way is a writable directory and no file stands in the way."""
    folder = out
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise NotADirectoryError(f"cannot write {option} {out}: {folder} is not a directory")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PermissionError(f"cannot write {option} {out}: directory {folder} is not writable")


def add_common(p: argparse.ArgumentParser, default_channel: str) -> None:
    p.add_argument("--channel", choices=sorted(PRESETS), default=default_channel)
    p.add_argument("--clients", type=bounded_int(1, 127), default=1)
    add_duration(p, "--duration", 60 * US_PER_S, "virtual time to simulate")
    p.add_argument("--initial", type=energy, default=10 * UJ_PER_J)
    p.add_argument("--duplicate", type=probability, help="override the channel's duplication")
    p.add_argument("--reorder", type=probability, help="override the channel's reordering")
    p.add_argument("--corrupt", type=probability, help="override the channel's bit flips")
    p.add_argument("--burst", type=probability, help="Gilbert-Elliott: P(good -> bad) per frame")
    p.add_argument("--delay-ms", type=milliseconds, help="mean one-way delay (plain: ms)")
    p.add_argument("--jitter-ms", type=milliseconds, help="uniform +- jitter (plain: ms)")
    p.add_argument(
        "--delay-dist",
        choices=["uniform", "exp"],
        help="per-frame delay: uniform in delay +- jitter, or exponential with mean delay",
    )
    p.add_argument(
        "--timeout-ms", type=milliseconds, help="response timeout (plain: ms; default: channel's)"
    )
    p.add_argument("--retries", type=bounded_int(0, 20), default=1, help="N (the paper: 1)")
    p.add_argument("--commit-ratio", type=probability, default=0.5)
    p.add_argument(
        "--return-every",
        type=duration_or_zero,
        default=5 * US_PER_S,
        metavar="TIME",
        help="mean time between returns, 0 off (default 5s; plain numbers are seconds)",
    )
    p.add_argument("--out", type=Path, required=True, help="output directory")


def sim_config(args: argparse.Namespace, loss: float | None = None) -> SimConfig:
    model = channel(
        args.channel,
        loss=loss,
        duplicate=args.duplicate,
        reorder=args.reorder,
        corrupt=args.corrupt,
        burst_enter=args.burst,
        delay_us=args.delay_ms,
        jitter_us=args.jitter_ms,
        delay=args.delay_dist,
    )
    return SimConfig(
        channel=model,
        clients=args.clients,
        duration_s=args.duration / US_PER_S,
        initial=args.initial,
        commit_ratio=args.commit_ratio,
        return_every_s=args.return_every / US_PER_S,
        timeout_us=args.timeout_ms,
        retries=args.retries,
    )
