"""``canergy demo`` end to end: ledger identity, verdicts, stop conditions, captures, CLI errors."""

from __future__ import annotations

import json
import random
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import cantools
import pytest
from can.interfaces.virtual import VirtualBus

from canergy.cli import main
from canergy.codec import Codec, DecodeError
from canergy.core import Supervisor
from canergy.demo import DemoConfig, format_report, run_demo
from canergy.demo.run import TICK_US, DemoRun
from canergy.demo.virtual_net import VirtualNetwork
from canergy.faults import FaultInjector, FaultProfile
from canergy.messages import QUANTUM_UJ, StatusRequest

DBC = Path(__file__).parent.parent / "dbc" / "canergy.dbc"
TERMS = (
    "supervisor_usable_uj",
    "supervisor_reserved_uj",
    "clients_usable_uj",
    "spent_uj",
    "returns_in_flight_uj",
)


def run_json(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, dict]:
    code = main(["demo", "--json", *args])
    return code, json.loads(capsys.readouterr().out)


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    """``canergy demo`` in its own process, so python-can's exit-time warnings reach stderr."""
    argv = [sys.executable, "-m", "canergy", "demo", *args]
    return subprocess.run(argv, capture_output=True, text=True, timeout=120)


def assert_identity(r: dict) -> None:
    held = sum(r[k] for k in TERMS) - r["overlap_uj"]
    assert r["initial_uj"] + r["injected_uj"] == held + r["dissipated_uj"]
    assert all(isinstance(r[k], int) for k in (*TERMS, "overlap_uj", "dissipated_uj"))


def test_acceptance_run(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    log = tmp_path / "out.log"
    code, r = run_json(capsys, "--nodes", "5", "--loss", "0.3", "--seed", "7", "--log", str(log))
    assert code == 0 and r["passive"] is True and r["finished"] is True
    assert_identity(r)
    assert r["dissipated_uj"] >= 0 and r["min_dissipated_uj"] >= 0
    assert set(r["nodes"]) == {"1", "2", "3", "4", "5"}
    assert sum(n["committed"] for n in r["nodes"].values()) > 0
    db = cantools.database.load_file(str(DBC))
    codec, frames, refused = Codec(), 0, 0
    for frame in can.LogReader(str(log)):
        db.decode_message(frame.arbitration_id, frame.data)  # every frame is in the DBC
        frames += 1
        try:
            codec.decode(frame.arbitration_id, frame.data)
        except DecodeError:
            refused += 1
    assert frames == r["frames_sent"] - r["frames_lost"] + r["frames_duplicated"]
    assert refused == r["decode_errors"] <= r["frames_corrupted"]
    assert r["decode_errors"] > 0, "the run corrupts frames; the CRC must refuse them"


def test_paper_variant_generates_energy_on_the_documented_seed(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, r = run_json(capsys, "--variant", "paper", "--seed", "5")
    assert code == 1 and r["passive"] is False and r["dissipated_uj"] < 0
    assert_identity(r)
    code, hardened = run_json(capsys, "--seed", "5")
    assert code == 0 and hardened["passive"] is True


@pytest.mark.parametrize("seed", range(6))
def test_hardened_is_passive_under_harsh_faults(
    capsys: pytest.CaptureFixture[str], seed: int
) -> None:
    code, r = run_json(
        capsys,
        "--seed",
        str(seed),
        "--loss",
        "0.5",
        "--duplicate",
        "0.2",
        "--reorder",
        "0.2",
        "--corrupt",
        "0.05",
        "--resets",
        "6",
        "--transactions",
        "120",
    )
    assert code == 0 and r["min_dissipated_uj"] >= 0 and r["finished"]
    assert_identity(r)


def test_same_seed_same_run(capsys: pytest.CaptureFixture[str]) -> None:
    assert run_json(capsys, "--seed", "11")[1] == run_json(capsys, "--seed", "11")[1]
    assert run_json(capsys, "--seed", "11")[1] != run_json(capsys, "--seed", "12")[1]


@pytest.mark.parametrize(
    ("variant", "seed", "faults"),
    [
        ("hardened", 1, FaultProfile()),
        ("hardened", 4, FaultProfile(loss=0.4, duplicate=0.1, reorder=0.1)),
        ("paper", 5, FaultProfile(loss=0.1, duplicate=0.05, reorder=0.05)),
        ("paper", 7, FaultProfile(loss=0.4, duplicate=0.1, reorder=0.1)),
    ],
)
def test_a_finished_run_did_all_its_work_and_settled(
    variant: str, seed: int, faults: FaultProfile
) -> None:
    cfg = DemoConfig(variant=variant, seed=seed, faults=faults, transactions=80)
    r = run_demo(cfg)
    assert r.finished and r.virtual_us <= cfg.duration_us
    assert r.transactions_started == cfg.transactions  # the budget lasts for all of them
    assert r.ledger.supervisor_reserved == 0, "a transaction was still open"
    assert all(u < QUANTUM_UJ for u in r.client_usable.values()), "a client kept energy"
    if variant == "hardened":  # the paper's returns are never acknowledged: lost ones stay
        assert r.ledger.returns_in_flight == 0, "a return was still unacknowledged"


def test_the_work_ends_when_the_budget_runs_out() -> None:
    r = run_demo(DemoConfig(initial=5 * QUANTUM_UJ, transactions=50, seed=1))
    assert r.finished and 0 < r.transactions_started < 50
    assert all(u < QUANTUM_UJ for u in r.client_usable.values())


@pytest.mark.parametrize("seed", [2, 3])
def test_a_run_stops_at_the_first_settled_tick_within_its_duration(seed: int) -> None:
    cfg = DemoConfig(seed=seed, transactions=40)
    r = run_demo(cfg)
    assert r.finished and r.virtual_us % TICK_US == 0, "a run stops on a tick"
    exact = run_demo(replace(cfg, duration_us=r.virtual_us))
    assert exact.finished and exact.as_json() == r.as_json()
    cut = run_demo(replace(cfg, duration_us=r.virtual_us - 1))
    assert not cut.finished
    assert r.virtual_us - 1 < cut.virtual_us <= r.virtual_us - 1 + TICK_US


def test_a_run_that_never_settles_stops_at_its_duration_limit() -> None:
    cfg = DemoConfig(seed=1, duration_us=2_000_000, faults=FaultProfile(loss=0.9))
    r = run_demo(cfg)
    limit = cfg.duration_us
    assert not r.finished and limit < r.virtual_us <= limit + TICK_US
    assert "stopped at the duration limit" in format_report(r)


@contextmanager
def lossy_run(**settings: Any) -> Iterator[DemoRun]:
    """A run of node 1 driven by hand, on a network that loses every frame."""
    injector = FaultInjector(FaultProfile(loss=1.0), random.Random(0))
    with VirtualNetwork(Codec(), injector) as net:
        yield DemoRun(DemoConfig(nodes=(1,), **settings), net)


def hold_energy(run: DemoRun) -> None:
    """Node 1 holds 5 mJ (out of nowhere: only the conditions are asked, not the ledger)."""
    run.clients[1].state = replace(run.clients[1].state, usable=5 * QUANTUM_UJ)


def lose_a_return(run: DemoRun) -> None:
    hold_energy(run)
    run.give_back(1, 5 * QUANTUM_UJ)


def lose_an_intention(run: DemoRun) -> None:
    run.carry_out(run.sup_ep, run.sup.begin(1, QUANTUM_UJ, run.now))


def keep_a_frame_in_flight(run: DemoRun) -> None:
    run.net.injector.profile = FaultProfile()
    run.net.send(run.sup_ep, StatusRequest(1, 1), run.now)


@pytest.mark.parametrize(
    "disturb", [hold_energy, lose_a_return, lose_an_intention, keep_a_frame_in_flight]
)
def test_any_one_unfinished_thing_keeps_a_run_from_settling(
    disturb: Callable[[DemoRun], None],
) -> None:
    with lossy_run() as run:
        assert run.settled()
        disturb(run)
        assert not run.settled()


def test_the_work_is_done_once_every_transaction_began_and_ended() -> None:
    with lossy_run(transactions=1) as run:
        assert not run.work_done()
        lose_an_intention(run)
        run.started = 1
        assert not run.work_done(), "the transaction is still open"
        while (timer := run.sup.get_timer()) is not None:  # re-sends, then a write-off
            run.carry_out(run.sup_ep, run.sup.handle_timer(timer))
        assert run.sup.is_quiescent() and run.work_done()


def test_the_work_is_done_when_no_budget_is_left_and_no_return_can_refill_it() -> None:
    with lossy_run(initial=0, transactions=5) as run:
        assert run.work_done()
        lose_a_return(run)
        assert not run.work_done(), "the pending return may still refill the budget"


def test_each_phase_ends_on_the_first_tick_its_condition_holds(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    asked: dict[str, list[tuple[int, bool]]] = {"work_done": [], "settled": []}

    def spy(name: str) -> Callable[[DemoRun], bool]:
        real = getattr(DemoRun, name)

        def ask(run: DemoRun) -> bool:
            asked[name].append((run.now, real(run)))
            return asked[name][-1][1]

        return ask

    for name in asked:
        monkeypatch.setattr(DemoRun, name, spy(name))
    r = run_demo(DemoConfig(seed=3, transactions=40))
    work, drain = asked["work_done"], asked["settled"]
    assert r.finished and work and drain
    assert [held for _, held in work] == [False] * (len(work) - 1) + [True]
    assert [held for _, held in drain] == [False] * (len(drain) - 1) + [True]
    times = [t for t, _ in work] + [t for t, _ in drain[1:]]
    assert times == list(range(0, r.virtual_us + 1, TICK_US)), "one question per tick"
    assert drain[0][0] == work[-1][0], "the drain begins on the tick the work was found done"


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".csv", ".trc"])
def test_captures_in_other_python_can_formats(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, suffix: str
) -> None:
    log = tmp_path / f"capture{suffix}"
    _, r = run_json(capsys, "--transactions", "20", "--log", str(log))
    ids = [m.arbitration_id for m in can.LogReader(str(log)) if not m.is_error_frame]
    assert len(ids) == r["frames_sent"] - r["frames_lost"] + r["frames_duplicated"]
    assert all(Codec().is_canergy_id(i) for i in ids)


def test_human_report(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--transactions", "30", "--nodes", "3"]) == 0
    out = capsys.readouterr().out
    assert "verdict: PASSIVE" in out and "dissipated" in out
    assert main(["demo", "--variant", "paper", "--seed", "5"]) == 1
    assert "verdict: NOT PASSIVE" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--loss", "1.5"], "outside 0..1"),
        (["--loss", "lots"], "not a probability"),
        (["--initial", "10W"], "unknown energy unit"),
        (["--nodes", "0"], "outside 1..127"),
        (["--node-ids", "5-2"], "bad node range"),
        (["--variant", "optimistic"], "invalid choice"),
        (["--transactions", "0"], "outside"),
    ],
)
def test_bad_values_are_clear_errors(
    capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["demo", *args])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("log", "problem"),
    [
        ("no/such/dir/x.log", "does not exist"),
        ("x.pcap", 'unknown log format ".pcap"'),
        (".", "is a directory"),
    ],
)
def test_a_bad_log_path_fails_before_any_bus_opens(tmp_path: Path, log: str, problem: str) -> None:
    path = tmp_path / log
    out = run_cli("--transactions", "5", "--log", str(path))
    assert out.returncode == 2 and out.stdout == ""
    (line,) = out.stderr.splitlines()  # in particular no "VirtualBus was not properly shut down"
    assert line.startswith(f"canergy demo: error: --log {path}: ") and problem in line
    assert not any(tmp_path.iterdir())


def test_a_grant_too_large_for_a_frame_names_its_options_in_joules(tmp_path: Path) -> None:
    log = tmp_path / "x.log"
    out = run_cli("--initial", "1000J", "--transactions", "5", "--log", str(log))
    assert out.returncode == 2
    (line,) = out.stderr.splitlines()
    assert "--initial 1000.000000 J over --transactions 5" in line
    assert "at most 65.535000 J" in line and "µJ" not in line
    assert not log.exists()


@pytest.fixture
def buses(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[list[Any], list[Any]]]:
    """Every python-can bus opened, and every one shut down, while the test runs."""
    opened: list[Any] = []
    shut: list[Any] = []
    open_bus, shutdown = can.Bus, VirtualBus.shutdown

    def recording_bus(*args: Any, **kwargs: Any) -> Any:
        opened.append(open_bus(*args, **kwargs))
        return opened[-1]

    def recording_shutdown(bus: VirtualBus) -> None:
        shut.append(bus)
        shutdown(bus)

    monkeypatch.setattr(can, "Bus", recording_bus)
    monkeypatch.setattr(VirtualBus, "shutdown", recording_shutdown)
    yield opened, shut


@pytest.mark.parametrize("fails", [False, True])
def test_every_bus_is_shut_down_and_a_failed_run_leaves_no_empty_capture(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    buses: tuple[list[Any], list[Any]],
    fails: bool,
) -> None:
    def refuse(*args: Any) -> None:
        raise RuntimeError("refused")

    if fails:  # the first grant fails, before any frame was captured
        monkeypatch.setattr(Supervisor, "begin", refuse)
    log = tmp_path / "run.log"
    cfg = DemoConfig(nodes=(1, 2), transactions=5, log=log)
    if fails:
        with pytest.raises(RuntimeError, match="refused"):
            run_demo(cfg)
    else:
        run_demo(cfg)
    opened, shut = buses
    assert len(opened) == 4  # the monitor, the supervisor and two nodes
    assert {id(b) for b in shut} == {id(b) for b in opened}
    assert log.exists() is not fails


def test_module_entry_point() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "canergy", "--version"], capture_output=True, text=True, check=True
    )
    assert out.stdout.startswith("canergy ")
