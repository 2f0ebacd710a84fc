"""The discrete-event simulator: determinism, the paper's scenario, channel models, sweeps."""

from __future__ import annotations

import csv
import json
import random
from dataclasses import replace
from pathlib import Path

import pytest

from canergy.cli import main
from canergy.faults import FaultCounters, FaultInjector
from canergy.sim.channel import PRESETS, Channel, ChannelModel, channel
from canergy.sim.engine import SimConfig, simulate
from canergy.sim.sweep import sweep

PAPER = SimConfig(duration_s=60)
SEEDS = range(40)


def test_a_seed_reproduces_the_run_exactly() -> None:
    config = replace(PAPER, strategy="paper", seed=3, trace=True)
    a, b = simulate(config), simulate(config)
    assert a.summary() == b.summary() and a.trace == b.trace and a.trace
    assert simulate(replace(config, seed=4)).trace != a.trace


def test_hardened_never_exceeds_the_initial_energy_on_the_paper_channel() -> None:
    committed = 0
    for seed in SEEDS:
        r = simulate(replace(PAPER, seed=seed))
        assert r.passivity_violations == 0 and r.max_generated_uj == 0, seed
        committed += r.committed
    assert committed > len(SEEDS)


def test_optimistic_dissipates_more_than_hardened() -> None:
    def dissipated(strategy: str) -> int:
        return sum(
            simulate(replace(PAPER, strategy=strategy, seed=s)).final_dissipated_uj for s in SEEDS
        )

    assert dissipated("optimistic") > 3 * dissipated("hardened")


def test_pessimistic_generates_energy_on_the_documented_seed() -> None:
    r = simulate(replace(PAPER, strategy="pessimistic", seed=1))
    assert r.passivity_violations > 0 and r.max_generated_uj == 485_000
    assert r.first_violation_s == pytest.approx(33.759782)


def test_the_papers_literal_rules_generate_energy_in_its_own_scenario() -> None:
    """docs/simulation.md: seed 6 creates energy from 16.88 s on, at worst 120 mJ (hazard (a))."""
    r = simulate(replace(PAPER, strategy="paper", seed=6))
    assert r.max_generated_uj == 120_000 and r.first_violation_s == pytest.approx(16.88181)


def test_corrupted_frames_are_rejected_by_the_real_codec() -> None:
    harsh = replace(PAPER, channel=channel("harsh"), duration_s=5, return_every_s=0.05)
    r = simulate(harsh)
    assert r.decode_errors > 0 and r.passivity_violations == 0 and r.committed > 50


def test_channel_streams_are_shared_across_strategies() -> None:
    config = replace(PAPER, channel=channel("lossy", loss=0.5), clients=3, seed=9, trace=True)
    firsts = []
    for name in ("hardened", "optimistic", "pessimistic"):
        frames = simulate(replace(config, strategy=name)).frames
        firsts.append([f["arrivals"] for f in frames if f["t"] == 0.0])  # the first intentions
    assert firsts[0] == firsts[1] == firsts[2] and len(firsts[0]) == 3
    assert len({len(a) for a in firsts[0]}) == 2  # one per node's own stream: some lost, some not
    fates = Channel(PRESETS["lossy"], 9)
    link = fates.link(1, to_client=True)
    assert link is fates.link(1, to_client=True) and link is not fates.link(1, to_client=False)


def test_gilbert_elliott_loses_in_bursts() -> None:
    def longest_run(model: ChannelModel) -> tuple[float, int]:
        link = FaultInjector(model, random.Random(5), FaultCounters())
        lost = [not link.fate(b"x") for _ in range(20_000)]
        run = best = 0
        for x in lost:
            run = run + 1 if x else 0
            best = max(best, run)
        return sum(lost) / len(lost), best

    bursty_rate, bursty_run = longest_run(ChannelModel(burst_enter=0.02, burst_leave=0.2))
    flat_rate, flat_run = longest_run(ChannelModel(loss=bursty_rate))
    assert abs(flat_rate - bursty_rate) < 0.02 and bursty_run > 2 * flat_run


def test_bad_channel_values_are_refused() -> None:
    with pytest.raises(ValueError, match="loss"):
        ChannelModel(loss=1.5)
    with pytest.raises(ValueError, match="unknown channel"):
        channel("nope")


def test_simulate_cli_writes_summary_trace_and_figures(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    argv = ["simulate", "--strategy", "all", "--channel", "paper", "--duration", "30"]
    assert main([*argv, "--seed", "1", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary) == {"hardened", "paper", "optimistic", "pessimistic"}
    keys = {
        "transactions_started",
        "committed",
        "aborted",
        "frames_sent",
        "passivity_violations",
        "max_generated_uj",
        "final_dissipated_uj",
        "worst_dissipated_uj",
    }
    for values in summary.values():
        assert all(isinstance(values[k], int) for k in keys)
        assert {"tx_time_p50_s", "tx_time_p99_s"} <= set(values)
    with open(out / "trace.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["event"] for r in rows} >= {"send", "send-lost", "receive", "ledger"}
    for name in [
        "budgets-overlay",
        *(f"{k}-{s}" for k in ("budgets", "sequence") for s in summary),
    ]:
        assert (out / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_small_sweep_on_all_cores(tmp_path: Path) -> None:
    base = SimConfig(channel=channel("ideal"), duration_s=2, return_every_s=0.02)
    points = sweep(base, ["hardened", "pessimistic"], [0.0, 0.3], range(4), progress=False)
    by = {(p.strategy, p.loss): p for p in points}
    assert all(p.seeds == 4 and p.transactions > 0 for p in points)
    assert by["hardened", 0.3].runs_generating == 0
    assert by["pessimistic", 0.3].runs_generating > 0
    assert by["hardened", 0.0].dissipated_uj == 0


def test_sweep_cli_writes_csv_and_plot(tmp_path: Path) -> None:
    argv = [
        "sweep",
        "--strategy",
        "hardened,optimistic",
        "--loss",
        "0,0.5",
        "--seeds",
        "2",
        "--duration",
        "1",
        "--return-every",
        "0.05",
        "--out",
        str(tmp_path),
    ]
    assert main(argv) == 0
    with open(tmp_path / "sweep.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 4 and (tmp_path / "sweep.png").stat().st_size > 1000


def test_exponential_delays_reorder_frames_without_creating_energy(tmp_path: Path) -> None:
    argv = [
        "simulate",
        "--channel",
        "ideal",
        "--delay-dist",
        "exp",
        "--delay-ms",
        "2",
        "--duration",
        "3",
        "--return-every",
        "0.05",
        "--out",
        str(tmp_path),
    ]
    assert main(argv) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())["hardened"]
    assert summary["passivity_violations"] == 0 and summary["committed"] > 100
