"""One supervisor over several buses (`canergy supervisor --bus ...`), and audits of captures
that hold more than one bus."""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import pytest
from support.live_rig import Loop

from canergy.auth.frames import FrameAuth, Layout
from canergy.auth.keys import Key, load_key
from canergy.ccore.supervisor import missing
from canergy.cli import main
from canergy.cli.shared.buses import bus_spec
from canergy.codec import Codec
from canergy.core import Supervisor
from canergy.core.state import Session, SupervisorState
from canergy.ledger import ledger_from_status
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.control import MAX_STATUS, request
from canergy.live.supervisor.multi_bus import BusPort, BusRouter
from canergy.live.supervisor.service import ServiceConfig
from canergy.live.supervisor.state_file import save_state
from canergy.messages import Ack, Commit, Committed, Direction, Intention, Message, Telemetry
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

J = 1_000_000


def _nodes(
    tmp: Path, channel: str, nodes: list[int], master: Key | None = None
) -> tuple[NodeHost, Loop]:
    """Emulated nodes on one virtual bus, their NV records in a directory of their own;
    ``master``: authenticated, with the node keys it derives."""
    tmp.mkdir()
    now = monotonic_us()
    host = NodeHost(
        [
            FirmwareNode(n, NvStore(tmp / f"{n}.nv", n, fsync=False), NodeConfig(), now)
            for n in nodes
        ]
    )
    bus = can.Bus(interface="virtual", channel=channel)
    codec = Codec()
    auth = None
    if master is not None:
        auth = FrameAuth(
            codec, Layout.CLASSIC, master.node_key, Direction.TO_CLIENT, host.freshness
        )
    runtime = BusRuntime(bus, host, codec=codec, receives=Direction.TO_CLIENT, auth=auth)
    return host, Loop(runtime)


class Buses:
    """Two virtual buses, nodes 1 and 2 on each, and the ``--bus`` options naming them."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.channels = {name: f"{name}-{uuid.uuid4().hex}" for name in ("chanA", "chanB")}
        self.hosts = {name: _nodes(tmp / name, ch, [1, 2]) for name, ch in self.channels.items()}

    def bus_args(self, *names: str) -> list[str]:
        out: list[str] = []
        for name in names or tuple(self.channels):
            out += ["--bus", f"{name}=virtual:{self.channels[name]}:1-2"]
        return out

    def node(self, bus: str, node: int) -> FirmwareNode:
        return self.hosts[bus][0].nodes[node]

    def halt(self) -> None:
        for _, loop in self.hosts.values():
            loop.halt()


@contextmanager
def _supervisor(tmp: Path, argv: list[str]) -> Iterator[Path]:
    """`canergy supervisor ARGV` in a thread; yields its control socket, stops it at the end
    and checks it exited 0."""
    control = tmp / "ctl.sock"
    result: list[int] = []
    thread = threading.Thread(
        target=lambda: result.append(main(["supervisor", *argv, "--control", str(control)]))
    )
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while not control.exists() and thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert control.exists(), "the supervisor never opened its control socket"
        yield control
        assert request(control, {"stop": True}, 30) == {"stopping": True}
    finally:
        thread.join(timeout=60)
    assert result == [0]


def _grant(control: Path, node: object, amount: int) -> dict[str, Any]:
    return request(control, {"grant": {"node": node, "amount_uj": amount}}, 30)


def test_one_budget_serves_two_buses_and_restarts_from_its_file(tmp_path: Path) -> None:
    buses = Buses(tmp_path)
    state, status = tmp_path / "s.json", tmp_path / "status.json"
    common = ["--initial", "10J", "--state", str(state), "--status-file", str(status)]
    common += ["--max-grant", "3J", "--no-fsync"]
    try:
        with _supervisor(tmp_path, [*buses.bus_args(), *common]) as control:
            a = _grant(control, "chanA/1", 2_500_000)
            b = _grant(control, "chanB/1", 1_500_000)
            assert a["outcome"] == "COMMITTED" and a["node"] == "chanA/1", a
            assert b["outcome"] == "COMMITTED" and b["node"] == "chanB/1", b
            assert "name its bus" in _grant(control, 1, 1000)["error"]  # two buses: which 1?
            assert "no bus named" in _grant(control, "chanC/1", 1000)["error"]
            assert "not managed" in _grant(control, "chanA/9", 1000)["error"]
        # each bus's node 1 got its own grant; node 2 on either bus nothing
        assert buses.node("chanA", 1).client.state.usable == 2_500_000
        assert buses.node("chanB", 1).client.state.usable == 1_500_000
        assert buses.node("chanA", 2).client.state.credited == 0
        assert buses.node("chanB", 2).client.state.credited == 0
        final = json.loads(status.read_text())
        assert list(final["nodes"]) == ["chanA/1", "chanA/2", "chanB/1", "chanB/2"]
        assert final["nodes"]["chanA/1"]["delivered_uj"] == 2_500_000
        assert final["nodes"]["chanB/1"]["delivered_uj"] == 1_500_000
        assert final["usable_uj"] == 6_000_000 and final["conservation"]["holds"]
        assert list(final["buses"]) == ["chanA", "chanB"]
        per_bus = [final["buses"][name]["frames_sent"] for name in ("chanA", "chanB")]
        assert min(per_bus) >= 2 and final["frames_sent"] == sum(per_bus)  # INTENTION, COMMIT
        books = ledger_from_status(
            final,
            {
                name: [n.status() for n in host.nodes.values()]
                for name, (host, _) in buses.hosts.items()
            },
        )
        assert books.passive and books.dissipated == 0, books.as_json()
        files = []
        for name, (host, _) in buses.hosts.items():
            for number, node in host.nodes.items():
                path = tmp_path / f"{name}-{number}.json"
                path.write_text(json.dumps(node.status()))
                files.append(f"{name}={path}")
        assert main(["ledger", "--level", str(status), *files]) == 0  # BUS=FILE per client
        from firmware_model.__main__ import status as emulator_status

        emulators = []  # python -m firmware_model --nodes 1-2 --status-file: one file per bus
        for name, (host, loop) in buses.hosts.items():
            path = tmp_path / f"{name}-emulator.json"
            path.write_text(json.dumps(emulator_status(host, loop.runtime)))
            emulators.append(f"{name}={path}")
        assert main(["ledger", "--level", str(status), *emulators]) == 0
        assert main(["ledger", "--level", str(status), *files[1:]]) == 2  # one client missing
        saved = json.loads(state.read_text())
        assert list(saved["sessions"]) == ["chanA/1", "chanA/2", "chanB/1", "chanB/2"]

        # a restart with the buses given the other way round: the books follow the names
        argv = [*buses.bus_args("chanB", "chanA"), *common]
        with _supervisor(tmp_path, argv) as control:
            grant = ["grant", "--control", str(control), "--node", "chanB/2", "--amount", "1J"]
            assert main(grant) == 0  # `canergy grant` names the node by its bus too
            assert _grant(control, "chanA/1", 500_000)["outcome"] == "COMMITTED"
        final = json.loads(status.read_text())
        assert final["usable_uj"] == 4_500_000
        assert final["nodes"]["chanA/1"]["delivered_uj"] == 3_000_000
        assert final["nodes"]["chanB/1"]["delivered_uj"] == 1_500_000
        assert final["nodes"]["chanB/2"]["delivered_uj"] == 1_000_000
        assert buses.node("chanB", 2).client.state.usable == 1_000_000
        assert buses.node("chanA", 2).client.state.credited == 0
    finally:
        buses.halt()


@pytest.mark.parametrize("core", ["c", "auto"])
def test_the_compiled_core_runs_over_several_buses(tmp_path: Path, core: str) -> None:
    """``--core c`` (and ``auto``, where it is built) with two ``--bus``: the C core runs, no
    fallback to Python, and its frame path takes each bus's answers."""
    if missing() is not None:
        pytest.fail(f"the compiled core is not built: {missing()}")
    buses = Buses(tmp_path)
    status = tmp_path / "status.json"
    argv = [*buses.bus_args(), "--core", core, "--state", str(tmp_path / "s.json")]
    argv += ["--status-file", str(status), "--no-fsync"]
    try:
        with _supervisor(tmp_path, argv) as control:
            taken = []
            for node, amount in (("chanA/2", 700_000), ("chanB/2", 300_000)):
                assert _grant(control, node, amount)["outcome"] == "COMMITTED"
                taken.append(
                    request(control, {"status": True}, 30, max_answer=MAX_STATUS)[
                        "frame_path_frames"
                    ]
                )
    finally:
        buses.halt()
    final = json.loads(status.read_text())
    assert (final["core"], final["frame_path"]) == ("c", "c") and "frame_path_off" not in final
    assert 2 <= taken[0] < taken[1] <= final["frame_path_frames"], taken  # ACK, COMMITTED each
    assert buses.node("chanA", 2).client.state.usable == 700_000
    assert buses.node("chanB", 2).client.state.usable == 300_000
    assert final["usable_uj"] == 9_000_000 and final["conservation"]["holds"]


def test_one_bus_given_with_bus_takes_a_plain_node_id_too(tmp_path: Path) -> None:
    channel = f"solo-{uuid.uuid4().hex}"
    host, loop = _nodes(tmp_path / "nodes", channel, [3])
    status = tmp_path / "status.json"
    argv = ["--bus", f"virtual:{channel}:3", "--state", str(tmp_path / "s.json")]
    try:
        with _supervisor(tmp_path, [*argv, "--status-file", str(status), "--no-fsync"]) as ctl:
            answer = _grant(ctl, 3, 1_000_000)
            assert answer["outcome"] == "COMMITTED" and answer["node"] == f"{channel}/3"
    finally:
        loop.halt()
    assert list(json.loads(status.read_text())["nodes"]) == [f"{channel}/3"]  # named: channel
    assert host.nodes[3].client.state.usable == 1_000_000


@pytest.mark.parametrize("core", ["python", "c"])
def test_authenticated_buses_check_each_node_with_its_own_counters(
    tmp_path: Path, core: str
) -> None:
    """--auth over two buses: each port finds its node's freshness under its session key. On
    the C core each bus's answers are verified, ruled and signed in C (no fallback)."""
    if core == "c" and missing() is not None:
        pytest.fail(f"the compiled core is not built: {missing()}")
    assert main(["keys", "-o", str(tmp_path / "m.key")]) == 0
    master = load_key(tmp_path / "m.key")
    channels = {name: f"auth-{name}-{uuid.uuid4().hex}" for name in ("a", "b")}
    hosts = {
        name: _nodes(tmp_path / name, channels[name], [node], master)
        for name, node in (("a", 1), ("b", 2))
    }
    argv = [f"--bus=a=virtual:{channels['a']}:1", f"--bus=b=virtual:{channels['b']}:2"]
    argv += ["--auth", str(tmp_path / "m.key"), "--state", str(tmp_path / "s.json")]
    argv += ["--core", core]
    status = tmp_path / "status.json"
    taken = []
    try:
        with _supervisor(tmp_path, [*argv, "--status-file", str(status), "--no-fsync"]) as ctl:
            for node, amount in (("a/1", 700_000), ("b/2", 300_000)):
                assert _grant(ctl, node, amount)["outcome"] == "COMMITTED"
                taken.append(
                    request(ctl, {"status": True}, 30, max_answer=MAX_STATUS)["frame_path_frames"]
                )
    finally:
        for _, loop in hosts.values():
            loop.halt()
    assert hosts["a"][0].nodes[1].client.state.usable == 700_000
    assert hosts["b"][0].nodes[2].client.state.usable == 300_000
    final = json.loads(status.read_text())
    assert final["intrusions"] == 0 and final["auth_failures"] == {}, final["auth_failures"]
    assert (final["core"], final["frame_path"]) == (core, core)
    if core == "c":  # each bus's ACK and COMMITTED at least
        assert taken[0] >= 2 and taken[0] + 2 <= taken[1] <= final["frame_path_frames"], taken
    else:
        assert taken == [0, 0]


def test_with_a_key_a_node_id_on_two_buses_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--auth derives each node's key from the one master key and its id: node 1 on two buses
    would be two sessions under one key. Refused by the builder's check (``check_session_keys``)
    before the state file is written, in the builder's words."""
    assert main(["keys", "-o", str(tmp_path / "m.key")]) == 0
    capsys.readouterr()
    state = tmp_path / "s.json"
    argv = ["supervisor", "--bus=a=virtual:x:1-2", "--bus=b=virtual:y:1", "--state", str(state)]
    assert main([*argv, "--auth", str(tmp_path / "m.key")]) == 2
    err = capsys.readouterr().err
    assert "node 1 is on bus a and on bus b under the same key" in err, err
    assert "give every node a different id" in err and len(err.splitlines()) == 1, err
    assert not state.exists()


def _books(sessions: tuple[Session, ...]) -> SupervisorState:
    return SupervisorState(10 * J, 10 * J - sum(s.delivered for s in sessions), 0, sessions)


@pytest.mark.parametrize(
    ("saved_buses", "keys", "argv", "message"),
    [
        (("chanA", "chanB"), (1, 257), ["--bus", "chanA=virtual:x:1"], "bus 'chanB' is not on"),
        (("chanA",), (3,), ["--bus", "chanA=virtual:x:1-2"], "chanA/3 not on the command line"),
        ((), (1,), ["--bus", "chanA=virtual:x:1"], "a node id without its bus"),
        (("chanA",), (1,), ["-i", "virtual", "-c", "x", "--nodes", "1"], "a bus/node key"),
    ],
)
def test_a_state_file_of_other_buses_is_refused(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    saved_buses: tuple[str, ...],
    keys: tuple[int, ...],
    argv: list[str],
    message: str,
) -> None:
    state = tmp_path / "s.json"
    save_state(
        state, _books(tuple(Session(k, delivered=J) for k in keys)), "hardened", buses=saved_buses
    )
    before = state.read_bytes()
    assert main(["supervisor", *argv, "--state", str(state)]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.splitlines()) == 1, err
    assert state.read_bytes() == before  # refused before anything was written


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--bus", "virtual:chan"], "expected [NAME=]INTERFACE:CHANNEL:NODES"),
        (["--bus", "virtual:chan:"], "expected [NAME=]INTERFACE:CHANNEL:NODES"),
        (["--bus", "virtual::1-2"], "expected [NAME=]INTERFACE:CHANNEL:NODES"),
        (["--bus", "nosuch:chan:1"], "unknown interface 'nosuch'"),
        (["--bus", "virtual:chan:0-3"], "ids are 1-127"),
        (["--bus", "virtual:chan:1-x"], "bad node list"),
        (["--bus", "=virtual:chan:1"], "the name before '=' is empty"),
        (["--bus", "virtual:a:1", "--nodes", "1"], "not with --nodes"),
        (["--bus", "virtual:a:1", "-i", "virtual", "-c", "a"], "not with -i/--interface, -c"),
        (["--bus", "x=virtual:a:1", "--bus", "x=virtual:b:1"], "two buses are named 'x'"),
        (["--bus", "virtual:a:1", "--bus", "b=virtual:a:2"], "virtual:a is given twice"),
        (["--bus", "virtual:a:1", "--canopen"], "--canopen work on one bus"),
        (["--bus", "virtual:a:1-2", "--bus", "virtual:b:2", "--auth", "k"], "node 2 is on bus a"),
    ],
)
def test_bad_bus_options_get_clear_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    try:
        code = main(["supervisor", *argv, "--state", str(tmp_path / "s.json")])
    except SystemExit as exc:
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    assert code == 2 and message in err, err
    assert not (tmp_path / "s.json").exists()


def test_a_bus_that_cannot_open_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    channel = f"ok-{uuid.uuid4().hex}"
    argv = ["supervisor", "--bus", f"virtual:{channel}:1", "--bus", "tty=slcan:/nonexistent:2"]
    assert main([*argv, "--state", str(tmp_path / "s.json")]) == 2
    assert "--bus tty: cannot open the CAN bus" in capsys.readouterr().err


def test_grant_names_a_node_by_its_bus_only_through_a_supervisor(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["grant", "--node", "can1/5", "--amount", "1J", "--state", str(tmp_path / "s.json")]
    assert main([*argv, "-i", "virtual", "-c", uuid.uuid4().hex]) == 2
    assert "through a running supervisor (--control)" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["grant", "--node", "can1/0", "--amount", "1J", "--control", "x"])
    assert "expected a node id 1-127 or BUS/NODE" in capsys.readouterr().err


def test_a_channel_may_hold_colons() -> None:
    spec = bus_spec("socketcand:10.0.0.1:29536:1-3,9")
    assert (spec.name, spec.interface, spec.channel) == ("10.0.0.1:29536", "socketcand", spec.name)
    assert spec.nodes == (1, 2, 3, 9)
    assert bus_spec("left=pcan:PCAN_USBBUS1:5").name == "left"


class _Sent:
    """Stands for a bus runtime: keeps what would be sent."""

    def __init__(self) -> None:
        self.messages: list[Message] = []

    def send_messages(self, messages: list[Message]) -> None:
        self.messages += messages


def test_ports_map_nodes_to_session_keys_and_back() -> None:
    """Node 1 on bus 1 is session 1 << 8 | 1: what it reports lands there, what the core sends
    it leaves on bus 1 as node 1; only the first port runs the deadlines."""
    core = Supervisor((1, 257), 10 * J)
    now = monotonic_us()
    service = build_service(core, ServiceConfig(bus_names=("a", "b")), now)
    router = BusRouter()
    sent = [_Sent(), _Sent()]
    router.runtimes = sent  # type: ignore[assignment]
    first, second = (BusPort(service, i, router, deadlines=i == 0) for i in (0, 1))
    assert second.next_wakeup() is None and second.on_wakeup(now) == ()
    assert first.next_wakeup() is not None
    assert second.on_message(Telemetry(1, 0, 0), now) == ()
    assert service.nodes[257].heard.heard_at == now and service.nodes[1].heard.heard_at is None
    answers: list[dict[str, Any]] = []
    service.request_grant(257, J, answers.append)
    first.on_wakeup(now)
    assert sent[0].messages == [] and [type(m) for m in sent[1].messages] == [Intention]
    assert sent[1].messages[0].node == 1 and core.session(257).reserved == J
    second.on_message(Ack(1, 1), now)  # acknowledged: the service commits at once
    assert isinstance(sent[1].messages[-1], Commit) and sent[1].messages[-1].node == 1
    second.on_message(Committed(1, 1), now)
    assert answers == [{"node": "b/1", "tx": 1, "outcome": "COMMITTED", "amount_uj": J}]
    assert core.session(1).delivered == 0 and core.session(257).delivered == J


# -- captures of several buses ---------------------------------------------------------------

CODEC = Codec()


def _exchange(channel: str, node: int, amount_mj: int, t: float) -> list[can.Message]:
    """One committed transaction of ``node`` on ``channel``."""
    msgs: list[Message] = [
        Intention(node, 1, amount_mj, 0),
        Ack(node, 1),
        Commit(node, 1, amount_mj),
        Committed(node, 1),
    ]
    frames = []
    for i, msg in enumerate(msgs):
        ident, data = CODEC.encode(msg)
        frames.append(
            can.Message(timestamp=t + 2 * i, arbitration_id=ident, data=data, channel=channel)
        )
    return frames


def _two_buses(path: Path, forged: Message | None = None) -> None:
    """Node 5 on can0 and node 5 on can1, each with its own transaction 1, interleaved."""
    frames = sorted(
        [*_exchange("can0", 5, 500, 1.0), *_exchange("can1", 5, 700, 2.0)],
        key=lambda f: f.timestamp,
    )
    if forged is not None:
        ident, data = CODEC.encode(forged)
        frames.append(can.Message(timestamp=20.0, arbitration_id=ident, data=data, channel="can1"))
    with can.Logger(str(path)) as log:
        for frame in frames:
            log.on_message_received(frame)


@pytest.mark.parametrize(("suffix", "names"), [(".log", ("can0", "can1")), (".blf", ("0", "1"))])
def test_the_audit_keeps_two_buses_nodes_apart(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], suffix: str, names: tuple[str, str]
) -> None:
    path = tmp_path / f"two{suffix}"
    _two_buses(path)
    assert main(["audit", str(path), "--json"]) == 0  # one node would show two tx 1 versions
    report = json.loads(capsys.readouterr().out)
    assert list(report["nodes"]) == [f"{names[0]}/5", f"{names[1]}/5"]
    granted = [report["nodes"][f"{name}/5"]["granted_uj"] for name in names]
    assert granted == [500_000, 700_000] and report["passive"]
    assert main(["audit", str(path)]) == 0
    rows = [line.split()[0] for line in capsys.readouterr().out.splitlines()[2:4]]
    assert rows == [f"{names[0]}/5", f"{names[1]}/5"]


def test_a_forgery_on_one_bus_is_named_with_its_bus(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "forged.log"
    _two_buses(path, forged=Commit(5, 2, 65535))  # on can1, for a tx never intended there
    assert main(["audit", str(path), "--json"]) == 1
    (violation,) = json.loads(capsys.readouterr().out)["violations"]
    assert violation["node"] == "can1/5" and "never was on the bus" in violation["what"]
    assert main(["decode", str(path), "--audit", "--color", "never"]) == 0
    flagged = [line for line in capsys.readouterr().out.splitlines() if line.startswith("!!")]
    assert len(flagged) == 1 and flagged[0].startswith("!! can1/5: COMMIT for tx 2"), flagged


def test_a_one_channel_capture_keeps_plain_node_ids(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "one.log"
    with can.Logger(str(path)) as log:
        for frame in _exchange("can0", 5, 500, 1.0):
            log.on_message_received(frame)
    assert main(["audit", str(path), "--json"]) == 0
    assert list(json.loads(capsys.readouterr().out)["nodes"]) == ["5"]
