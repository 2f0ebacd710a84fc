"""``canergy demo`` end to end: ledger identity, verdicts, captures, CLI errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import can
import cantools
import pytest

from canergy.cli import main
from canergy.codec import Codec, DecodeError

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


def test_module_entry_point() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "canergy", "--version"], capture_output=True, text=True, check=True
    )
    assert out.stdout.startswith("canergy ")
