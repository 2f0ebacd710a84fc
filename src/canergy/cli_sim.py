"""``canergy simulate`` and ``canergy sweep``: the paper's case study, and Monte Carlo over it."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from canergy.cli_args import (
    SEED_MAX,
    add_duration,
    bounded_int,
    duration_or_zero,
    energy,
    max_processes,
    milliseconds,
    probability,
    seed,
)
from canergy.extras import require
from canergy.sim.channel import PRESETS, channel
from canergy.sim.engine import STRATEGIES, SimConfig, simulate
from canergy.units import UJ_PER_J, US_PER_S

ALL = list(STRATEGIES)
SEEDS_MAX = 100_000
"""Most seeds per point of a sweep (the README's largest sweep runs 2,000)."""
LOSS_POINTS_MAX = 100
"""Most loss rates in one sweep."""


def _strategies(text: str) -> list[str]:
    names = ALL if text == "all" else [s.strip() for s in text.split(",")]
    unknown = [n for n in names if n not in STRATEGIES]
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown strategy {unknown[0][:24]!r} (all, {', '.join(ALL)})"
        )
    return names


def _floats(text: str) -> list[float]:
    parts = text.split(",")
    if len(parts) > LOSS_POINTS_MAX:
        raise argparse.ArgumentTypeError(f"{len(parts)} rates, at most {LOSS_POINTS_MAX}")
    return [probability(part) for part in parts]


def _check_out_dir(out: Path, option: str = "--out") -> None:
    """Fail now, not after the runs, unless ``out`` is a directory or can be made one: the
    nearest existing folder on its way is a writable directory and no file stands in the way."""
    folder = out
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise NotADirectoryError(f"cannot write {option} {out}: {folder} is not a directory")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PermissionError(f"cannot write {option} {out}: directory {folder} is not writable")


def _common(p: argparse.ArgumentParser, default_channel: str) -> None:
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


def add_parsers(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "simulate",
        help="discrete-event simulation of the paper's case study (and more)",
        description="Simulate one supervisor and K clients in virtual time over a channel model "
        "and write DIR/summary.json, DIR/trace.csv and PNG figures.",
    )
    p.add_argument("--strategy", type=_strategies, default=["hardened"], help="S, S1,S2 or all")
    p.add_argument("--seed", type=seed, default=0, help="0..2**32-1 (default 0)")
    p.add_argument("--loss", type=probability, help="override the channel's frame loss")
    _common(p, "paper")

    s = sub.add_parser(
        "sweep",
        help="Monte Carlo over loss rates, many seeds per point, all cores",
        description="Run every strategy at every loss rate for --seeds seeds and write "
        "DIR/sweep.csv and DIR/sweep.png (generated and dissipated energy per transaction).",
    )
    s.add_argument("--strategy", type=_strategies, default=ALL, help="S, S1,S2 or all")
    s.add_argument("--loss", type=_floats, default=[0.0, 0.1, 0.3, 0.5], help="e.g. 0,0.1,0.3")
    s.add_argument(
        "--seeds",
        type=bounded_int(1, SEEDS_MAX),
        default=100,
        help=f"seeds per point (default 100, at most {SEEDS_MAX:,})",
    )
    s.add_argument(
        "--first-seed",
        type=seed,
        default=0,
        help="seeds run from here (default 0); the last is at most 2**32-1",
    )
    s.add_argument(
        "--processes",
        type=bounded_int(1, max_processes()),
        help=f"default: all cores (at most {max_processes()} here: 4 per core, at most 256)",
    )
    _common(s, "ideal")


def _config(args: argparse.Namespace, loss: float | None = None) -> SimConfig:
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


def run_simulate(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from canergy.sim.outputs import write_outputs

    require("plot")  # the figures are written last: say so before simulating
    _check_out_dir(args.out)
    base = replace(_config(args, args.loss), seed=args.seed, trace=True)
    results = [simulate(replace(base, strategy=s)) for s in args.strategy]
    summary = write_outputs(results, args.out)
    print(json.dumps(summary, indent=2))
    generated = [s for s, v in summary.items() if v["passivity_violations"]]
    if generated:
        print(f"energy generated by: {', '.join(generated)}", file=sys.stderr)
    return 0


def run_sweep(args: argparse.Namespace) -> int:
    from canergy.sim.sweep import plot, sweep, write_csv

    require("plot")  # sweep.png is written last: say so before sweeping
    if args.first_seed + args.seeds - 1 > SEED_MAX:
        raise ValueError(
            f"--first-seed {args.first_seed} with --seeds {args.seeds} runs past seed {SEED_MAX}"
        )
    _check_out_dir(args.out)
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    points = sweep(_config(args), args.strategy, args.loss, seeds, processes=args.processes)
    args.out.mkdir(parents=True, exist_ok=True)
    write_csv(points, args.out / "sweep.csv")
    plot(points, args.out / "sweep.png")
    total = sum(p.transactions for p in points)
    for p in points:
        row = p.row()
        print(
            f"{p.strategy:<12} loss {p.loss:<5} tx {p.transactions:>9,}  generating runs "
            f"{p.runs_generating:>4}/{p.seeds}  generated/tx "
            f"{row['generated_per_tx_uj'] / 1000:>9.3f} mJ  "
            f"dissipated/tx {row['dissipated_per_tx_uj'] / 1000:>9.3f} mJ"
        )
    print(f"{total:,} transactions in {len(points) * args.seeds:,} runs -> {args.out}/sweep.csv")
    return 0


COMMANDS = {"simulate": run_simulate, "sweep": run_sweep}
