"""canergy-gateway's bus below as the port wires it (ports/linux/gateway_below.c,
gateway_report.c, gateway_storage.c), on this kernel without SocketCAN: the port's files with a
harness for main() (tests/support/gateway_below_harness.c: the bus below on a socketpair, time
given here). What the vcan suite (tests/test_vcan_c_gateway*.py) cannot show on this machine:
a JOIN below held until the node's TELEMETRY, a replayed or forged JOIN refused while the node
reports its books (nothing written off), frames in the supervisor's own direction reported,
refused frames told on stderr at most once a second, a start from a record older than a node's
admission afresh paid for and told, and a status file that is JSON.
"""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import tempfile
import threading
import zlib
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from support.firmware_build import GATEWAY_PORT
from support.firmware_build import harness as built_harness

from canergy.auth.keys import new_master, write_key
from canergy.codec import Codec
from canergy.live.supervisor.joins import JOIN_HOLD_US
from canergy.messages import Admit, Commit, Debit, Join, Message, Return, Telemetry

CODEC = Codec()


@pytest.fixture(scope="module")
def harness(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The harness (the bus below) built under ASan and UBSan."""
    return built_harness(
        "gateway_below_harness",
        tmp_path_factory.mktemp("harness"),
        ["gateway_below.c", *GATEWAY_PORT],
    )


def rx(msg: Message) -> str:
    arbitration_id, data = CODEC.encode(msg)
    return f"rx {arbitration_id:08X}#{data.hex().upper()}"


class Run:
    """One harness run: its script's frames out, stderr, and the status written last."""

    def __init__(
        self,
        harness: Path,
        tmp: Path,
        script: list[str],
        *extra: str,
        nv: Path | None = None,
        code: int = 0,
    ) -> None:
        """``nv``: the NV file (default: a new one); ``code``: the exit status expected."""
        tmp = Path(tempfile.mkdtemp(dir=tmp))
        self.status_path = tmp / "gw.json"
        self.nv = tmp / "gw.nv" if nv is None else nv
        args = _args(harness, self.nv, self.status_path, *extra)
        done = subprocess.run(
            args, input="\n".join([*script, "status"]) + "\n", capture_output=True, text=True
        )
        assert done.returncode == code, done.stderr
        self.lines = done.stdout.splitlines()
        self.stderr = done.stderr

    def sent(self, type_code: int) -> list[str]:
        return [
            x
            for x in self.lines
            if x.startswith("tx ") and int(x[3:11], 16) >> 8 & 0xF == type_code
        ]

    def status(self) -> dict[str, Any]:
        loaded: dict[str, Any] = json.loads(self.status_path.read_text())
        return loaded


def _args(harness: Path, nv: Path, status: Path, *extra: str) -> list[str]:
    """The harness's command line: nodes 1 and 2 below, a 0.5 J target each."""
    args = [str(harness), "--node", "20", "--nodes", "1-2", "-c", "down"]
    args += ["--upstream-channel", "up", "--nv", str(nv)]
    args += ["--status-file", str(status), "--target", "0.5J"]
    return [*args, "--response-timeout", "30", *extra]  # a grant stays in flight


ADMIT, INTENTION = 0x7, 0x1


def _started(node: int = 1) -> list[str]:
    """Node 1 starts without books: its JOIN and JOINING TELEMETRY, admitted after the hold;
    then it reports its books (level 0) and the tick tops it up."""
    return [
        "inject 5000000",
        "at 1000",
        rx(Join(node, 0x0042)),
        rx(Telemetry(node, 0, Telemetry.JOINING, 0)),
        f"at {1000 + JOIN_HOLD_US - 1}",
        f"at {1000 + JOIN_HOLD_US}",
        rx(Telemetry(node, 0, 0, 0)),
        "tick",
    ]


def test_a_join_below_waits_the_hold_and_a_replay_while_the_node_reports_is_refused(
    harness: Path, tmp_path: Path
) -> None:
    t = 1000 + JOIN_HOLD_US
    script = _started()
    script += [
        rx(Join(1, 0x0007)),  # an earlier life's, with its TELEMETRY without books
        rx(Telemetry(1, 0, Telemetry.JOINING, 0)),
        f"at {t + 100_000}",
        rx(Telemetry(1, 0, 0, 0)),  # the node, with its books, at once
        f"at {t + 10 * JOIN_HOLD_US}",
    ]
    run = Run(harness, tmp_path, script)
    assert len(run.sent(ADMIT)) == 1  # at its start only
    assert len(run.sent(INTENTION)) == 1  # the top-up, in flight all along
    node = run.status()["nodes"]["1"]
    assert node["admitted"] == 1 and node["written_off"] == 0 and node["intrusions"] == 1
    assert node["open_tx"] == 1 and node["reserved_uj"] == 500_000
    assert "intrusion #1 for node 1 below: Join(node=1, nonce=7) (a JOIN in its name" in run.stderr
    held = Run(harness, tmp_path, _started()[:5])  # up to 1 µs before the hold is over
    assert held.lines == [] and held.status()["nodes"]["1"]["joins_held"] == 1


def test_a_replay_while_the_node_stays_silent_is_admitted_after_the_hold(
    harness: Path, tmp_path: Path
) -> None:
    """The residual (docs/gateways.md): nobody objects within 500 ms, the JOIN is admitted and
    the grant in flight written off (never created)."""
    t = 1000 + JOIN_HOLD_US
    script = _started()
    script += [rx(Join(1, 0x0007)), rx(Telemetry(1, 0, Telemetry.JOINING, 0))]
    script += [f"at {t + JOIN_HOLD_US - 1}", f"at {t + JOIN_HOLD_US}"]
    early = Run(harness, tmp_path, script[:-1])  # 1 µs before the hold is over: held
    assert len(early.sent(ADMIT)) == 1 and early.status()["nodes"]["1"]["written_off"] == 0
    run = Run(harness, tmp_path, script)
    assert len(run.sent(ADMIT)) == 2
    node = run.status()["nodes"]["1"]
    assert node["admitted"] == 2 and node["written_off"] == 1 and node["intrusions"] == 0


def test_frames_in_the_supervisors_direction_below_are_intrusions(
    harness: Path, tmp_path: Path
) -> None:
    """Someone else's INTENTION for node 1 below (a second supervisor, a spoofer): reported as
    an intrusion on stderr and in the status, no decode error, nothing moves."""
    run = Run(harness, tmp_path, _started())
    intention = run.sent(INTENTION)[0][3:]
    again = Run(harness, tmp_path, [*_started(), f"rx {intention}"])
    status = again.status()
    assert status["nodes"]["1"]["intrusions"] == 1 and status["intrusions"] == 1
    assert status["downstream_bus"]["decode_errors"] == 0
    assert "(a frame only this supervisor sends)" in again.stderr
    assert status["nodes"]["1"]["reserved_uj"] == 500_000


def test_refusals_below_are_rated_and_told_at_most_once_a_second(
    harness: Path, tmp_path: Path
) -> None:
    """--auth (classic): keyless RETURNs in node 1's name, each refused when the next one
    displaces it without its MAC frame; the first told at once with its frame, then one line a
    second with what was refused since; the status rates them per node and reason; a frame in the
    supervisor's direction is refused too (not verified here)."""
    master = tmp_path / "master.key"
    keys = [sys.executable, "-m", "canergy", "keys", "-o", str(master)]
    made = subprocess.run(keys, capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert made.returncode == 0, made.stderr
    forged = rx(Return(1, 1, 5))
    script = ["at 1000"] + [forged] * 3 + ["at 600000", forged, "tick", "at 1200000"]
    script += [forged, "tick", rx(Commit(1, 1, 100))]  # the supervisor's direction
    script += ["at 1300000"]
    run = Run(harness, tmp_path, script, "--auth", str(master))
    lines = [x for x in run.stderr.splitlines() if "refused" in x]
    assert len(lines) == 2, run.stderr
    assert "refused a frame for node 1 below: frame without a MAC" in lines[0]
    assert "refused 3 frame(s) below in the last 1.2 s" in lines[1], lines[1]
    assert "node 1: frame without a MAC 3); 4 since start, none acted on" in lines[1]
    refused = run.status()["refused"]
    assert refused["total"] == 5 and refused["by_node"]["1"]["total"] == 5
    reasons = refused["by_node"]["1"]["reasons"]
    assert reasons["frame without a MAC"]["count"] == 4
    assert reasons["a frame in the supervisor's direction (not verified)"]["count"] == 1
    assert refused["per_s"] > 0 and refused["first_at_us"] == 1000
    assert run.status()["nodes"]["1"]["refused"] == 5
    assert run.status()["auth_failures"] == {"frame without a MAC": 4}


def test_a_damaged_cut_short_or_oversize_nv_file_is_refused_by_name(
    harness: Path, tmp_path: Path
) -> None:
    """The NV file's two slots (nv.c: a counter and a CRC each): the newest damaged beside a
    valid one is a write not finished (the older taken, said on stderr); both damaged, or the
    file cut within its first slot, is refused with the slot named (it started without books
    before); a file longer than two slots is not this gateway's. An older copy itself is the
    witnessed rules' to find (tests/test_vcan_c_gateway_old_copy.py)."""
    first = Run(harness, tmp_path, _started())
    image = first.nv.read_bytes()
    slot = len(image) // 2
    assert len(image) == 2 * slot and first.status()["state_writes"] >= 2

    def run(data: bytes, code: int) -> Run:
        nv = tmp_path / f"edited-{code}-{len(data)}.nv"
        nv.write_bytes(data)
        return Run(harness, tmp_path, [], nv=nv, code=code)

    def flipped(data: bytes, at: int) -> bytes:
        return data[:at] + bytes([data[at] ^ 0x01]) + data[at + 1 :]

    counters = [int.from_bytes(image[k * slot + 4 : k * slot + 8], "little") for k in (0, 1)]
    newest = counters.index(max(counters))
    torn = run(flipped(image, newest * slot + 100), 0)
    older = counters[1 - newest]
    assert f"slot {newest} cut short or its CRC does not hold" in torn.stderr
    assert f"the other slot, counter {older}, taken" in torn.stderr
    both = run(flipped(flipped(image, 100), slot + 100), 2)
    assert f"--nv {both.nv}: slot 0 and 1: cut short or its CRC does not hold" in both.stderr
    assert both.nv.read_bytes() == flipped(flipped(image, 100), slot + 100)  # left as it was
    cut = run(image[: slot // 2], 2)
    assert f"--nv {cut.nv}: slot 0: cut short" in cut.stderr
    long = run(image + b"{}", 2)
    assert f"{2 * slot + 2} bytes is not a canergy-gateway NV file" in long.stderr


def test_with_a_key_its_nv_slots_are_sealed_and_an_edited_one_is_set_aside(
    harness: Path, tmp_path: Path
) -> None:
    """``--auth``: each slot sealed under a key derived from the gateway's master key
    (canergy/nv.h, "Sealed image"). Its upstream usable raised in the newest slot, the CRC
    recomputed (what a local user without the key can do): that slot is set aside and the older,
    genuine one taken (its books, not 900 J); both edited: refused, the file left as it was."""
    master = tmp_path / "gw.key"
    write_key(master, new_master(1))
    auth = ("--auth", str(master))
    first = Run(harness, tmp_path, ["inject 5000000", "inject 5000000"], *auth)
    image = first.nv.read_bytes()
    slot = (len(image) - 16) // 2
    assert len(image) == 2 * slot + 16 and first.status()["injected_uj"] == 10_000_000
    assert Run(harness, tmp_path, [], *auth, nv=first.nv).status()["injected_uj"] == 10_000_000
    image = first.nv.read_bytes()  # that start saved again (a start below)
    counters = [int.from_bytes(image[k * slot + 4 : k * slot + 8], "little") for k in (0, 1)]
    newest = counters.index(max(counters))

    def edited(data: bytes, k: int) -> bytes:
        at = k * slot
        body = (
            data[at : at + 8] + (900_000_000).to_bytes(4, "little") + data[at + 12 : at + slot - 4]
        )
        return data[:at] + body + zlib.crc32(body).to_bytes(4, "little") + data[at + slot :]

    nv = tmp_path / "edited.nv"
    nv.write_bytes(edited(image, newest))
    taken = Run(harness, tmp_path, [], *auth, nv=nv)
    assert f"slot {newest}: the seal does not hold" in taken.stderr, taken.stderr
    assert taken.status()["upstream"]["usable_uj"] == 0  # the genuine record's
    both = edited(edited(image, 0), 1)
    nv.write_bytes(both)
    refused = Run(harness, tmp_path, [], *auth, nv=nv, code=2)
    assert f"--nv {nv}: slot 0 and 1: the seal does not hold" in refused.stderr
    assert nv.read_bytes() == both
    assert "not sealed" in Run(harness, tmp_path, [], *auth, nv=_plain(first), code=2).stderr


def _plain(run: Run) -> Path:
    """The slots of ``run``'s NV file without their seals: a record never sealed."""
    image = run.nv.read_bytes()
    plain = run.nv.with_name("plain.nv")
    plain.write_bytes(image[:-16])
    return plain


def test_the_witnesss_evidence_below_is_told_on_stderr(harness: Path, tmp_path: Path) -> None:
    """No key: a RETURN forged in node 1's name for more than its books let it hold is refuted
    (``returns_refuted``) and told as an intrusion on stderr, as ``canergy gateway`` tells it; a
    TELEMETRY whose witness count moved is counted too (told only as a node's 100th)."""
    script = [*_started(), rx(Return(1, 1, 60_000)), rx(Telemetry(1, 0, 0, 0, witness=1))]
    run = Run(harness, tmp_path, script)
    node = run.status()["nodes"]["1"]
    assert node["returns_refuted"] == 1 and node["intrusions"] == 2
    assert (
        "intrusion #1 for node 1 below: Return(node=1, seq=1, amount_mj=60000) (no honest node"
        in run.stderr
    )
    assert "intrusion #2" not in run.stderr  # a node's first is told, then one in 100
    assert run.status()["intrusions_first_at_us"] == 1000 + JOIN_HOLD_US


def _started_saying(rules: int) -> list[str]:
    """``_started()`` with every TELEMETRY of node 1 carrying the rules flag ``rules``."""
    said = {rx(t): rx(replace(t, flags=t.flags | rules)) for t in _STARTED_TELEMETRY}
    return [said.get(line, line) for line in _started()]


_STARTED_TELEMETRY = (Telemetry(1, 0, Telemetry.JOINING, 0), Telemetry(1, 0, 0, 0))


@pytest.mark.parametrize("below", ["hardened", "witnessed"])
def test_a_node_below_with_other_rules_is_granted_nothing_and_told_once(
    harness: Path, tmp_path: Path, below: str
) -> None:
    """Review rv3, F3: a TELEMETRY saying other client rules than ``--rules`` (its WITNESSED
    flag) stops the node's top-ups; told once on stderr, counted in the status. The same node
    saying the gateway's rules is topped up."""
    other = Telemetry.WITNESSED if below == "hardened" else 0
    ours = Telemetry.WITNESSED - other
    script = [*_started_saying(other), rx(Telemetry(1, 0, other, 0)), "tick"]
    run = Run(harness, tmp_path, script, "--rules", below)
    assert run.sent(INTENTION) == []
    assert run.status()["nodes"]["1"]["variant_mismatch"] == 3
    said = f"node 1 below runs the {'witnessed' if other else 'hardened'} rules, this gateway the"
    assert run.stderr.count(said) == 1
    run = Run(harness, tmp_path, _started_saying(ours), "--rules", below)
    assert len(run.sent(INTENTION)) == 1 and run.status()["nodes"]["1"]["variant_mismatch"] == 0


def test_a_witnessed_node_below_whose_window_is_used_up_is_resynced(
    harness: Path, tmp_path: Path
) -> None:
    """--rules witnessed: node 1 below answers none of its top-ups' INTENTIONs (lost, closed by
    their timeouts), so W stays at 0 while tx runs on; the 65th begin is beyond the window
    (tx + 1 > W + B, B = 64) and the port re-syncs that node alone: one SYNC (an ADMIT with a
    nonce the node did not send) and no further INTENTION until the node answers."""
    witnessed = Telemetry.WITNESSED
    script = [*_started_saying(witnessed), "inject 100000000"]  # each lost grant written off
    t = 1000 + JOIN_HOLD_US
    for _ in range(700):
        t += 500_000  # past a response timeout: the INTENTION re-sent, then closed
        script += [f"at {t}", rx(Telemetry(1, 0, witnessed, 0)), "tick"]
    run = Run(harness, tmp_path, script, "--rules", "witnessed", "--response-timeout", "10ms")
    begun = {CODEC.decode(*_frame(x)).tx for x in run.sent(INTENTION)}
    assert begun == set(range(1, 65)), (run.stderr[-3000:], run.status()["nodes"]["1"])
    admits = run.sent(ADMIT)
    assert len(admits) >= 2, run.lines[-5:]  # the JOIN's ADMIT, then the re-sync's SYNC
    joins_nonce = CODEC.decode(*_frame(admits[0])).nonce
    sync = CODEC.decode(*_frame(admits[1]))
    assert sync.node == 1 and sync.nonce != joins_nonce
    assert run.status()["nodes"]["1"]["resyncs"] == 1


def _frame(line: str) -> tuple[int, bytes]:
    """A harness output line ``tx IIIIIIII#DATA`` as an identifier and bytes."""
    ident, data = line[3:].split("#")
    return int(ident, 16), bytes.fromhex(data)


@pytest.mark.parametrize("numbers", [2, 32_766], ids=["restored", "forged-most"])
def test_a_start_from_a_record_older_than_a_nodes_admission_afresh_pays_and_says_so(
    harness: Path, tmp_path: Path, numbers: int
) -> None:
    """--rules witnessed: the gateway starts from a record of node 1 below (C as at its JOIN);
    the node answers the start's SYNC with books it cannot tell (Rc unknown) and counts afresh
    at q = C + 1 + ``numbers``, debit numbers this record never held (admitted afresh after
    it): ``numbers`` x 65.535 J leave the budget below for the node's Gs, a debt, and stderr
    names the node, the numbers and the amount. 32,766: the most a forged frame without a key
    can claim (2.15 MJ, past 32 bits of µJ). The SYNC's nonce is random: the harness is driven
    line by line."""
    witnessed = ("--rules", "witnessed")
    first = Run(harness, tmp_path, _started_saying(Telemetry.WITNESSED), *witnessed)
    status = tmp_path / "restarted.json"
    proc = subprocess.Popen(
        _args(harness, first.nv, status, *witnessed),
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdin is not None and proc.stdout is not None and proc.stderr is not None
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in proc.stdout or ()], daemon=True).start()
    try:
        proc.stdin.write("at 2000\n")
        proc.stdin.flush()
        sync = None
        while sync is None:  # the start's SYNC of node 1: an ADMIT with the start's nonce
            line = lines.get(timeout=30)
            msg = CODEC.decode(*_frame(line)) if line.startswith("tx ") else None
            sync = msg if isinstance(msg, Admit) and msg.node == 1 else None
        usable = json.loads(first.status_path.read_text())["usable_uj"]
        answers = [
            Debit.books(1, sync.nonce, None),
            Debit.counts(1, sync.nonce, (sync.seq + 1 + numbers) & 0xFFFF, 0, afresh=True),
        ]
        proc.stdin.write("\n".join(["at 3000", *(rx(m) for m in answers), "status"]) + "\n")
        proc.stdin.close()
        proc.wait(timeout=60)
        err = proc.stderr.read()
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    moved = numbers * 65_535_000
    assert (
        f"node 1 below holds {numbers} debit numbers this record never saw, with books that "
        "cannot say what it received" in err
    ), err
    assert f"{moved} uJ moved from the usable budget" in err
    assert json.loads(status.read_text())["usable_uj"] <= usable - moved, usable
