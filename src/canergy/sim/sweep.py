"""``canergy sweep``: Monte Carlo over loss rates (and duplication, clients), every core busy."""

from __future__ import annotations

import csv
import multiprocessing
import os
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TextIO

from canergy.extras import require
from canergy.sim.engine import SimConfig, simulate


@dataclass(frozen=True, slots=True)
class Run:
    strategy: str
    loss: float
    seed: int


def _one(task: tuple[SimConfig, Run]) -> tuple[Run, dict[str, Any]]:
    base, run = task
    config = replace(
        base,
        strategy=run.strategy,
        seed=run.seed,
        channel=replace(base.channel, loss=run.loss),
        trace=False,
    )
    return run, simulate(config).summary()


@dataclass(slots=True)
class Point:
    """Totals of one (strategy, loss) point over its seeds."""

    strategy: str
    loss: float
    seeds: int = 0
    transactions: int = 0
    committed: int = 0
    runs_generating: int = 0
    generated_uj: int = 0
    dissipated_uj: int = 0
    max_generated_uj: int = 0
    worst_seed: int | None = None

    def add(self, seed: int, s: dict[str, Any]) -> None:
        self.seeds += 1
        self.transactions += s["transactions_started"]
        self.committed += s["committed"]
        self.generated_uj += s["max_generated_uj"]
        self.dissipated_uj += max(0, s["final_dissipated_uj"])
        if s["passivity_violations"]:
            self.runs_generating += 1
        if s["max_generated_uj"] > self.max_generated_uj:
            self.max_generated_uj, self.worst_seed = s["max_generated_uj"], seed

    def row(self) -> dict[str, Any]:
        per_tx = max(1, self.transactions)
        return {
            "strategy": self.strategy,
            "loss": self.loss,
            "seeds": self.seeds,
            "transactions": self.transactions,
            "committed": self.committed,
            "runs_generating": self.runs_generating,
            "generated_per_tx_uj": round(self.generated_uj / per_tx, 1),
            "dissipated_per_tx_uj": round(self.dissipated_uj / per_tx, 1),
            "max_generated_uj": self.max_generated_uj,
            "worst_seed": "" if self.worst_seed is None else self.worst_seed,
        }


class Progress:
    """A one-line bar on a terminal, a line per 10 % otherwise."""

    def __init__(self, total: int, stream: TextIO = sys.stderr) -> None:
        self.total, self.done, self.stream = total, 0, stream
        self.tty = stream.isatty()
        self.started = self.last = time.monotonic()
        self.last_decile = -1

    def step(self) -> None:
        self.done += 1
        now = time.monotonic()
        decile = 10 * self.done // self.total
        if self.tty and (now - self.last > 0.2 or self.done == self.total):
            filled = 30 * self.done // self.total
            bar = "#" * filled + "." * (30 - filled)
            self.stream.write(f"\r[{bar}] {self.done}/{self.total} runs {now - self.started:.0f} s")
            self.last = now
        elif not self.tty and decile != self.last_decile:
            self.stream.write(f"sweep: {self.done}/{self.total} runs, {now - self.started:.0f} s\n")
            self.last_decile = decile
        if self.done == self.total and self.tty:
            self.stream.write("\n")
        self.stream.flush()


def sweep(
    base: SimConfig,
    strategies: Sequence[str],
    losses: Sequence[float],
    seeds: Iterable[int],
    *,
    processes: int | None = None,
    progress: bool = True,
) -> list[Point]:
    runs = [Run(s, loss, seed) for s in strategies for loss in losses for seed in seeds]
    points = {(s, loss): Point(s, loss) for s in strategies for loss in losses}
    bar = Progress(len(runs)) if progress else None
    tasks = [(base, run) for run in runs]
    workers = processes or os.cpu_count() or 1
    # spawn, not fork: a forked child of a process with threads (a GUI, a bus notifier, a test
    # runner) can inherit a held lock and hang
    with multiprocessing.get_context("spawn").Pool(workers) as pool:
        for run, summary in pool.imap_unordered(_one, tasks, chunksize=max(1, len(tasks) // 200)):
            points[(run.strategy, run.loss)].add(run.seed, summary)
            if bar is not None:
                bar.step()
    return list(points.values())


def write_csv(points: Sequence[Point], path: Path) -> None:
    rows = [p.row() for p in points]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def plot(points: Sequence[Point], path: Path) -> None:
    require("plot")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (gen, dis) = plt.subplots(1, 2, figsize=(11, 4))
    for name in dict.fromkeys(p.strategy for p in points):
        mine = sorted((p for p in points if p.strategy == name), key=lambda p: p.loss)
        losses = [p.loss for p in mine]
        gen.plot(losses, [p.row()["generated_per_tx_uj"] / 1000 for p in mine], "o-", label=name)
        dis.plot(losses, [p.row()["dissipated_per_tx_uj"] / 1000 for p in mine], "o-", label=name)
    gen.set_title("energy generated per transaction")
    dis.set_title("energy dissipated per transaction")
    for ax in (gen, dis):
        ax.set_xlabel("frame loss probability")
        ax.set_ylabel("mJ per transaction")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
