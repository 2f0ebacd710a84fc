"""`canergy gateway` as users run it: a root supervisor above, nodes below, on python-can's
virtual buses, frames lost and duplicated on the upstream leg; the gateway's one state file."""

from __future__ import annotations

import json
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support.live_rig import Loop

from canergy.cli import main
from canergy.codec import Codec
from canergy.core.gateway import Gateway, GatewayState
from canergy.core.hardened import CLIENT, SUPERVISOR
from canergy.core.state import ClientState, Outcome, Phase, Session, SupervisorState
from canergy.ledger import TreeLedger, ledger_from_status
from canergy.live.gateway.state import load_gateway, save_gateway
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.control import request
from canergy.live.supervisor.state_file import StateFileError
from canergy.messages import Admit, Commit, Direction, Intention
from firmware_model.actuator import PowerProfile
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

GW = 20
NODES = (1, 2, 3)


class Tree:
    """A root supervisor and a gateway (CLI runs in threads) and three emulated nodes."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.up, self.down = f"up-{uuid.uuid4().hex}", f"down-{uuid.uuid4().hex}"
        config = NodeConfig(power=PowerProfile.constant(2.0), return_above=900_000)
        now = monotonic_us()
        self.host = NodeHost(
            [FirmwareNode(n, NvStore(tmp / f"{n}.nv", n, fsync=False), config, now) for n in NODES]
        )
        bus = can.Bus(interface="virtual", channel=self.down)
        self.nodes = Loop(BusRuntime(bus, self.host, codec=Codec(), receives=Direction.TO_CLIENT))
        self.results: dict[str, int] = {}
        self.threads: dict[str, threading.Thread] = {}

    def start(self, name: str, argv: list[str], control: Path) -> None:
        def run() -> None:
            self.results[name] = main(argv)

        self.threads[name] = threading.Thread(target=run, daemon=True)
        self.threads[name].start()
        deadline = time.monotonic() + 30
        while not control.exists() and time.monotonic() < deadline:
            time.sleep(0.02)

    def start_root(self) -> None:
        t = self.tmp
        argv = ["supervisor", "-i", "virtual", "-c", self.up, "--nodes", str(GW)]
        argv += ["--initial", "30J", "--target", "4J", "--state", str(t / "root.json")]
        argv += ["--status-file", str(t / "root-status.json"), "--control", str(t / "root.sock")]
        self.start("root", [*argv, "--no-fsync", "--status-period", "100ms"], t / "root.sock")

    def start_gateway(self, *extra: str) -> None:
        t = self.tmp
        argv = ["gateway", "--node", str(GW), "--nodes", "1-3", "-i", "virtual", "-c", self.down]
        argv += ["--upstream-interface", "virtual", "--upstream-channel", self.up]
        argv += ["--state", str(t / "gw.json"), "--status-file", str(t / "gw-status.json")]
        argv += ["--control", str(t / "gw.sock"), "--target", "1J", "--return-above", "6J"]
        argv += ["--no-fsync", "--status-period", "100ms", "--telemetry-period", "50ms", *extra]
        self.start("gateway", argv, t / "gw.sock")

    def stop(self, name: str) -> None:
        assert request(self.tmp / f"{'gw' if name == 'gateway' else name}.sock", {"stop": True}, 30)
        self.threads[name].join(timeout=60)
        assert self.results.get(name) == 0

    def status(self, name: str) -> dict[str, Any]:
        return json.loads((self.tmp / f"{name}-status.json").read_text())  # type: ignore[no-any-return]

    def wait(self, what: Any, timeout: float = 60) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                if what():
                    return
            except (OSError, ValueError, KeyError):
                pass  # a status file not written yet
            time.sleep(0.05)
        raise AssertionError("timed out")

    def tree(self) -> TreeLedger:
        root, gw = self.status("root"), self.status("gw")
        nodes = [node.status() for node in self.host.nodes.values()]
        return TreeLedger(
            {
                "root": ledger_from_status(root, [gw["upstream"]]),
                "gateway": ledger_from_status(gw, nodes),
            },
            {"gateway": gw["link_gap_uj"]},
        )


@contextmanager
def tree(tmp: Path) -> Iterator[Tree]:
    t = Tree(tmp)
    try:
        yield t
    finally:
        for name in ("gateway", "root"):
            thread = t.threads.get(name)
            if thread is not None and thread.is_alive():
                sock = tmp / f"{'gw' if name == 'gateway' else name}.sock"
                request(sock, {"stop": True}, 30)
                thread.join(timeout=60)
        t.nodes.halt()


def test_a_tree_through_a_lossy_upstream_leg_creates_nothing(tmp_path: Path) -> None:
    with tree(tmp_path) as t:
        t.start_root()
        t.start_gateway("--upstream-loss", "0.15", "--upstream-duplicate", "0.1")
        drawn = lambda: sum(n.actuator.drawn_uj for n in t.host.nodes.values())  # noqa: E731
        t.wait(lambda: drawn() > 12_000_000)  # more than the root's target: topped up again
        gw = t.status("gw")
        assert gw["role"] == "gateway" and gw["link_gap_uj"] == 0
        assert gw["upstream"]["credited_uj"] > 4_000_000
        t.stop("gateway")
        t.stop("root")
        books = t.tree()
    assert books.passive, books.as_json()
    root = t.status("root")
    # written off at the root (its books count it delivered) is paid back with a later grant
    assert root["nodes"][str(GW)]["delivered_uj"] >= t.status("gw")["upstream"]["credited_uj"]


def test_a_restarted_gateway_continues_from_its_one_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with tree(tmp_path) as t:
        t.start_root()
        t.start_gateway()
        t.wait(lambda: t.status("gw")["upstream"]["credited_uj"] >= 4_000_000)
        # a second gateway on the same file while the first keeps it (review rv3): refused
        # before it reads the file, or both would spend one record
        bus = ["-i", "virtual", "-c", t.down, "--upstream-interface", "virtual"]
        second = ["gateway", "--node", str(GW), "--nodes", "1-3", *bus, "--upstream-channel"]
        assert main([*second, t.up, "--state", str(tmp_path / "gw.json"), "--no-fsync"]) == 2
        assert "is kept by another holder" in capsys.readouterr().err
        t.stop("gateway")
        before = json.loads((tmp_path / "gw.json").read_text())
        # its first start's JOIN (re-sent when the ADMIT is slow, each copy admitted), read from
        # a status the root wrote after the gateway stopped
        stopped_at = t.status("root")["uptime_s"]
        t.wait(lambda: t.status("root")["uptime_s"] >= stopped_at + 0.2)
        admitted = t.status("root")["nodes"][str(GW)]["admitted"]
        assert admitted >= 1
        t.start_gateway()
        t.wait(
            lambda: t.status("gw")["upstream"]["credited_uj"] > before["upstream"]["credited_uj"]
        )
        gw = t.status("gw")
        assert gw["upstream"]["joins"] == 0  # its books came back: no JOIN, nothing written off
        t.stop("gateway")
        t.stop("root")
        assert t.status("root")["nodes"][str(GW)]["admitted"] == admitted  # none at the restart
        books = t.tree()
    assert books.passive, books.as_json()


def test_the_ledger_command_closes_the_tree_from_status_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with tree(tmp_path) as t:
        t.start_root()
        t.start_gateway()
        t.wait(lambda: t.status("gw")["upstream"]["credited_uj"] >= 4_000_000)
        t.stop("gateway")
        t.stop("root")
    nodes = []
    for number, node in t.host.nodes.items():
        nodes.append(str(tmp_path / f"n{number}.json"))
        Path(nodes[-1]).write_text(json.dumps(node.status()))
    root, gw = str(tmp_path / "root-status.json"), str(tmp_path / "gw-status.json")
    argv = ["ledger", "--level", root, gw, "--level", gw, *nodes]
    assert main(argv) == 0
    assert "PASSIVE" in capsys.readouterr().out
    # a gateway whose roles disagree (energy made between them) is caught
    status = json.loads(Path(gw).read_text())
    status["injected_uj"] += 1000  # more below than ever left the upstream role
    Path(gw).write_text(json.dumps(status))
    assert main([*argv, "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["passive"] is False
    assert main(["ledger", "--level", root, nodes[0]]) == 2  # node 1 is not the root's client
    assert f"--level {root}: the ledger needs exactly one client" in capsys.readouterr().err
    assert main(["ledger", "--level", str(tmp_path / "gw.json")]) == 2  # a state file
    assert "not a supervisor's or gateway's status file" in capsys.readouterr().err


def _state(tmp: Path) -> tuple[Path, GatewayState]:
    gw = Gateway(GW, NODES)
    gw.books_lost(1, 0)
    gw.receive_upstream(Admit(GW, 1, 0, 0), 0)
    gw.receive_upstream(Intention(GW, 1, 3000, 0), 0)
    gw.receive_upstream(Commit(GW, 1, 3000), 0)
    gw.down.begin(2, 1_000_000, 0)
    path = tmp / "gw.json"
    save_gateway(path, gw.state, "hardened", fsync=False)
    return path, gw.state


def test_the_state_file_keeps_both_roles(tmp_path: Path) -> None:
    path, state = _state(tmp_path)
    loaded = load_gateway(path, "hardened", GW, NODES)
    assert loaded.up.spent == 3_000_000 and loaded.up.last_tx == 1
    assert loaded.down.injected == 3_000_000 and loaded.down.sessions[1].reserved == 1_000_000
    assert loaded.down.usable == state.down.usable == 2_000_000


def test_the_state_file_refuses_roles_that_disagree(tmp_path: Path) -> None:
    path, state = _state(tmp_path)
    up = replace(state.up, spent=state.up.spent - 1000)
    save_gateway(path, GatewayState(up, state.down), "hardened", fsync=False)
    with pytest.raises(StateFileError, match="roles disagree by 1000"):
        load_gateway(path, "hardened", GW, NODES)
    with pytest.raises(StateFileError, match="20, but this gateway is node 21"):
        _state(tmp_path)
        load_gateway(path, "hardened", 21, NODES)
    text = path.read_text().replace('"spent_uj":3000000', '"spent_uj":3000001')
    path.write_text(text)
    with pytest.raises(StateFileError, match="checksum"):
        load_gateway(path, "hardened", GW, NODES)


def test_a_gateway_that_was_joining_joins_again(tmp_path: Path) -> None:
    gw = Gateway(GW, NODES)
    path = tmp_path / "gw.json"
    save_gateway(path, gw.state, "hardened", fsync=False)  # blank, never admitted
    assert load_gateway(path, "hardened", GW, NODES).up.phase is Phase.JOINING
    gw.books_lost(1, 0)
    save_gateway(path, gw.state, "hardened", fsync=False)
    assert load_gateway(path, "hardened", GW, NODES).up.phase is Phase.JOINING
    path.write_text(path.read_text().replace('"credited_uj":0', '"credited_uj":5000'))
    with pytest.raises(StateFileError, match="joining has no upstream books"):
        load_gateway(path, "hardened", GW, NODES, accept_edited=True)


@pytest.mark.parametrize(
    ("field", "value", "why"),
    [
        ("usable_uj", 1000, "forwards what it is credited"),
        ("return_pending_uj", 500, "not a whole number of mJ"),
        ("return_pending_uj", 70_000_000, "above"),
        ("last_tx", -1, "negative"),
    ],
)
def test_the_state_file_refuses_an_upstream_record_no_gateway_writes(
    tmp_path: Path, field: str, value: int, why: str
) -> None:
    path, _ = _state(tmp_path)
    books = json.loads(path.read_text())
    books["upstream"][field] = value
    path.write_text(json.dumps(books))
    with pytest.raises(StateFileError, match=why):
        load_gateway(path, "hardened", GW, NODES, accept_edited=True)


def test_a_gateway_killed_before_it_was_admitted_joins_again(tmp_path: Path) -> None:
    """No supervisor above yet: the gateway waits for ADMIT; its file says it is joining, so
    after a restart it joins again instead of trusting a blank record."""
    with tree(tmp_path) as t:
        t.start_gateway()
        t.wait(lambda: t.status("gw")["upstream"]["joining"])
        t.stop("gateway")
        assert json.loads((tmp_path / "gw.json").read_text())["upstream"]["joining"] == 1
        t.start_root()
        t.start_gateway()
        t.wait(lambda: t.status("gw")["upstream"]["credited_uj"] > 0)
        assert t.status("gw")["upstream"]["joins"] == 1  # joined again at the restart


@settings(max_examples=100, deadline=None)
@given(
    up=st.builds(
        ClientState,
        node=st.just(GW),
        credited=st.integers(0, 10**12),
        last_tx=st.integers(1, 10**6),
        outcome=st.sampled_from(list(Outcome)),
        return_seq=st.integers(1, 10**6),
        return_pending=st.integers(0, 65_535).map(lambda mj: mj * 1000),
        credited_unknown=st.booleans(),
    ),
    delivered=st.lists(st.integers(0, 10**9), min_size=3, max_size=3),
    usable=st.integers(0, 10**9),
    withdrawn=st.integers(0, 10**9),
)
def test_the_file_keeps_every_field_the_rules_persist(
    up: ClientState, delivered: list[int], usable: int, withdrawn: int
) -> None:
    """Whatever the client's and the supervisor's rules persist comes back from the file."""
    sessions = tuple(Session(n, delivered=d) for n, d in zip(NODES, delivered, strict=True))
    injected = usable + sum(delivered) + withdrawn
    down = SupervisorState(0, usable, injected, sessions, withdrawn)
    state = GatewayState(replace(up, spent=injected - withdrawn), down)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "gw.json"
        save_gateway(path, state, "hardened", fsync=False)
        loaded = load_gateway(path, "hardened", GW, NODES)
    assert CLIENT.persistent(loaded.up) == CLIENT.persistent(state.up)
    assert [SUPERVISOR.persistent(s) for s in loaded.down.sessions] == [
        SUPERVISOR.persistent(s) for s in state.down.sessions
    ]
    assert (loaded.down.usable, loaded.down.injected, loaded.down.withdrawn) == (
        usable,
        injected,
        withdrawn,
    )


def _c_core() -> None:
    """These tests are about the compiled core: one not built fails them (as tests/test_build's
    frame-path test), never falls back to Python unnoticed."""
    from canergy.ccore.supervisor import missing

    if missing() is not None:
        pytest.fail(f"the compiled core is not built: {missing()}")


def test_the_gateway_runs_below_on_the_compiled_core_and_its_frame_path(tmp_path: Path) -> None:
    """By default (``--core auto``) the downstream role runs on the C core: the status says so,
    C's frame path takes the nodes' frames (``frame_path_frames`` grows), energy comes from
    above and goes back up as RETURNs, the nodes' RETURNs are held and credited, and a restart
    on either core takes the file the other wrote; the tree creates nothing."""
    _c_core()
    with tree(tmp_path) as t:
        t.start_root()
        t.start_gateway("--return-above", "2J", "--target", "3J")  # above what nodes keep
        t.wait(lambda: t.status("gw")["upstream"]["return_seq"] >= 1)  # a RETURN went up
        first = t.status("gw")
        assert (first["core"], first["frame_path"]) == ("c", "c")
        assert "frame_path_off" not in first and first["link_gap_uj"] == 0
        t.wait(lambda: t.status("gw")["frame_path_frames"] > first["frame_path_frames"] > 0)
        # the nodes' RETURNs, held for their TELEMETRY (--return-hold) in C, then credited
        t.wait(lambda: sum(n["returns_credited"] for n in t.status("gw")["nodes"].values()) > 0)
        t.stop("gateway")
        for core in ("python", "c"):  # the file the C core wrote, on the Python one, and back
            credited = json.loads((tmp_path / "gw.json").read_text())["upstream"]["credited_uj"]
            t.start_gateway("--return-above", "2J", "--target", "3J", "--core", core)
            t.wait(lambda c=credited: t.status("gw")["upstream"]["credited_uj"] > c)
            gw = t.status("gw")
            assert (gw["core"], gw["frame_path"], gw["upstream"]["joins"]) == (core, core, 0)
            t.stop("gateway")
        t.stop("root")
        books = t.tree()
        assert t.status("root")["nodes"][str(GW)]["returns_credited"] >= 1
    assert books.passive, books.as_json()


def test_gateway_core_c_is_refused_where_the_compiled_core_cannot_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--core c`` without the compiled core is an error naming why, before the state file is
    written; ``--core auto`` then runs the Python core."""
    import canergy.cli.shared.live

    monkeypatch.setattr(canergy.cli.shared.live, "missing", lambda: "not built here (a test)")
    argv = ["gateway", "--node", str(GW), "--nodes", "1-3", "-i", "virtual", "-c", "gw-down"]
    argv += ["--upstream-interface", "virtual", "--upstream-channel", "gw-up"]
    argv += ["--state", str(tmp_path / "gw.json"), "--core", "c"]
    assert main(argv) == 2
    assert "canergy gateway: error: --core c: not built here (a test)" in capsys.readouterr().err
    assert not (tmp_path / "gw.json").exists()
    with tree(tmp_path) as t:
        t.start_gateway("--core", "auto")
        t.wait(lambda: t.status("gw")["upstream"]["joining"])
        gw = t.status("gw")
        assert (gw["core"], gw["frame_path"]) == ("python", "python")
        t.stop("gateway")
