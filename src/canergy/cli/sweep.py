"""``canergy sweep``: Monte Carlo over loss rates, many seeds per point, all cores."""

from __future__ import annotations

import argparse

from canergy.argtypes import (
    SEED_MAX,
    bounded_int,
    max_processes,
    seed,
)
from canergy.cli.shared.sim import (
    ALL,
    add_common,
    check_out_dir,
    loss_rates,
    sim_config,
    strategies,
)
from canergy.cli.summaries import SUMMARIES
from canergy.extras import require

SEEDS_MAX = 100_000
"""Most seeds per point of a sweep (the README's largest sweep runs 2,000)."""


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    s = sub.add_parser(
        "sweep",
        help=SUMMARIES["sweep"],
        description="Run every strategy at every loss rate for --seeds seeds and write "
        "DIR/sweep.csv and DIR/sweep.png (generated and dissipated energy per transaction).",
    )
    s.add_argument("--strategy", type=strategies, default=ALL, help="S, S1,S2 or all")
    s.add_argument("--loss", type=loss_rates, default=[0.0, 0.1, 0.3, 0.5], help="e.g. 0,0.1,0.3")
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
    add_common(s, "ideal")
    s.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from canergy.sim.sweep import plot, sweep, write_csv

    require("plot")  # sweep.png is written last: say so before sweeping
    if args.first_seed + args.seeds - 1 > SEED_MAX:
        raise ValueError(
            f"--first-seed {args.first_seed} with --seeds {args.seeds} runs past seed {SEED_MAX}"
        )
    check_out_dir(args.out)
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    points = sweep(sim_config(args), args.strategy, args.loss, seeds, processes=args.processes)
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
