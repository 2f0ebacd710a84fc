"""`canergy gateway` in authenticated mode, leg by leg: upstream it is node GW of the root
supervisor with its own node key (derived from the root's master key), downstream the supervisor
of its nodes with a master key of its own; its state file is sealed with that master key. A root
supervisor (CLI, a thread), the gateway (CLI, a thread) and an emulated leaf node on python-can's
virtual buses, with a MAC on every frame of both legs: energy moves end to end, keyless forgeries
and replays on either leg move nothing and are counted, wrong keys are refused before anything is
opened. Without a key below, the gateway holds its nodes' RETURNs for their confirmation, as a
supervisor does, and a root without a key credits the gateway's own returns."""

from __future__ import annotations

import json
import os
import secrets
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import can
import pytest
from support.live_rig import Loop

from canergy.auth.frames import FrameAuth, Layout
from canergy.auth.keys import load_key
from canergy.ccore.supervisor import missing
from canergy.cli import build_parser, main
from canergy.cli.gateway import _config
from canergy.codec import Codec
from canergy.ledger import TreeLedger, ledger_from_status
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.control import request
from canergy.messages import Commit, Direction, Intention, Message, Return, ReturnAck
from firmware_model.actuator import PowerProfile
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

GW = 20
LEAF = 1
CODEC = Codec()
FAST = ["--no-fsync", "--status-period", "100ms", "--response-timeout", "100ms"]


def keys(tmp: Path) -> None:
    """root.key (the root's master), up/node-020.key (the gateway's node key, from root.key),
    gw.key (the gateway's own master), down/node-001.key (the leaf's, from gw.key)."""
    for master, node, folder in (("root.key", GW, "up"), ("gw.key", LEAF, "down")):
        assert main(["keys", "-o", str(tmp / master)]) == 0
        derive(tmp / master, node, tmp / folder)


def derive(master: Path, node: int, folder: Path) -> None:
    """``canergy keys --master MASTER --nodes NODE -o FOLDER``."""
    assert main(["keys", "--master", str(master), "--nodes", str(node), "-o", str(folder)]) == 0


def forged(msg: Message, layout: Layout | None) -> list[can.Message]:
    """What a participant without a key can build: the codec's frame, in the layout's shape
    with a MAC of zeros (no layout: the plain frame)."""
    arbitration_id, data = CODEC.encode(msg)
    if layout is Layout.FD:
        length = 16 if len(data) <= 4 else 20
        return [
            can.Message(
                arbitration_id=arbitration_id, is_fd=True, data=data + bytes(length - len(data))
            )
        ]
    frames = [can.Message(arbitration_id=arbitration_id, data=data)]
    if layout is Layout.CLASSIC:
        kind = 0x0 if msg.TYPE < 8 else 0x8
        mac_id = CODEC.id_base | kind << 8 | msg.node
        frames.append(can.Message(arbitration_id=mac_id, data=bytes([msg.TYPE]) + bytes(7)))
    return frames


class AuthTree:
    """root (node GW above) → gateway → leaf node LEAF; ``up``/``down``: each leg's layout (None:
    no key on that leg). Sniffers capture both legs; ``rogue_*`` send on them."""

    def __init__(self, tmp: Path, up: Layout | None, down: Layout | None, leaf: NodeConfig) -> None:
        self.tmp, self.up, self.down = tmp, up, down
        self.up_channel, self.down_channel = (
            f"gwa-up-{uuid.uuid4().hex}",
            f"gwa-down-{uuid.uuid4().hex}",
        )
        now = monotonic_us()
        node = FirmwareNode(LEAF, NvStore(tmp / "leaf.nv", LEAF, fsync=False), leaf, now)
        self.leaf = node
        self.host = NodeHost([node])
        down_fd = down is Layout.FD
        bus = can.Bus(
            interface="virtual",
            channel=self.down_channel,
            fd=down_fd,
            can_filters=CODEC.client_watch_filters(LEAF),
        )
        auth = None
        if down is not None:
            secret = load_key(tmp / "down" / f"node-{LEAF:03d}.key").node_key(LEAF)
            auth = FrameAuth(
                CODEC, down, lambda n: secret, Direction.TO_CLIENT, self.host.freshness
            )
            auth.join_fv[LEAF] = secrets.randbits(16) << 16 | node.client.state.nonce
        runtime = BusRuntime(bus, self.host, codec=CODEC, receives=Direction.TO_CLIENT, auth=auth)
        self.loop = Loop(runtime)
        up_fd = up is Layout.FD
        self.rogue_up = can.Bus(interface="virtual", channel=self.up_channel, fd=up_fd)
        self.rogue_down = can.Bus(interface="virtual", channel=self.down_channel, fd=down_fd)
        self.sniff_up = can.Bus(interface="virtual", channel=self.up_channel, fd=up_fd)
        self.sniff_down = can.Bus(interface="virtual", channel=self.down_channel, fd=down_fd)
        self.results: dict[str, int] = {}
        self.threads: dict[str, threading.Thread] = {}

    # -- processes ----------------------------------------------------------------------------
    def start(self, name: str, argv: list[str]) -> None:
        sock = self.tmp / f"{name}.sock"

        def run() -> None:
            self.results[name] = main(argv)

        self.threads[name] = threading.Thread(target=run, daemon=True)
        self.threads[name].start()
        deadline = time.monotonic() + 30
        while not sock.exists() and time.monotonic() < deadline:
            assert self.threads[name].is_alive(), f"{name} ended: {self.results.get(name)}"
            time.sleep(0.02)

    def start_root(self, *extra: str) -> None:
        t = self.tmp
        argv = ["supervisor", "-i", "virtual", "-c", self.up_channel, "--nodes", str(GW)]
        argv += ["--initial", "30J", "--state", str(t / "root.json")]
        argv += ["--status-file", str(t / "root-status.json"), "--control", str(t / "root.sock")]
        if self.up is not None:
            argv += ["--auth", str(t / "root.key"), *(["--fd"] if self.up is Layout.FD else [])]
        self.start("root", [*argv, *FAST, *extra])

    def gateway_argv(self, *extra: str) -> list[str]:
        t = self.tmp
        argv = ["gateway", "--node", str(GW), "--nodes", str(LEAF)]
        argv += ["-i", "virtual", "-c", self.down_channel]
        argv += ["--upstream-interface", "virtual", "--upstream-channel", self.up_channel]
        argv += ["--state", str(t / "gw.json"), "--status-file", str(t / "gw-status.json")]
        argv += ["--control", str(t / "gw.sock"), "--telemetry-period", "50ms"]
        argv += ["--upstream-response-timeout", "100ms"]
        if self.up is not None:
            argv += ["--upstream-auth", str(t / "up" / f"node-{GW:03d}.key")]
            argv += ["--upstream-fd"] if self.up is Layout.FD else []
        if self.down is not None:
            argv += ["--auth", str(t / "gw.key"), *(["--fd"] if self.down is Layout.FD else [])]
        return [*argv, *FAST, *extra]

    def start_gateway(self, *extra: str) -> None:
        self.start("gw", self.gateway_argv(*extra))

    def stop(self, name: str) -> None:
        assert request(self.tmp / f"{name}.sock", {"stop": True}, 30)
        self.threads[name].join(timeout=60)
        assert self.results.get(name) == 0

    def grant(self, name: str, node: int, amount_uj: int) -> dict[str, Any]:
        payload = {"grant": {"node": node, "amount_uj": amount_uj}}
        return request(self.tmp / f"{name}.sock", payload, 60)

    def status(self, name: str) -> dict[str, Any]:
        return dict(json.loads((self.tmp / f"{name}-status.json").read_text()))

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

    # -- the books ------------------------------------------------------------------------------
    def tree(self) -> TreeLedger:
        root, gw = self.status("root"), self.status("gw")
        return TreeLedger(
            {
                "root": ledger_from_status(root, [gw["upstream"]]),
                "gateway": ledger_from_status(gw, [self.leaf.status()]),
            },
            {"gateway": gw["link_gap_uj"]},
        )

    def close(self) -> None:
        for name in ("gw", "root"):
            thread = self.threads.get(name)
            if thread is not None and thread.is_alive():
                request(self.tmp / f"{name}.sock", {"stop": True}, 30)
                thread.join(timeout=60)
        self.loop.halt()
        for bus in (self.rogue_up, self.rogue_down, self.sniff_up, self.sniff_down):
            bus.shutdown()


@pytest.fixture
def make_tree(tmp_path: Path) -> Any:
    made: list[AuthTree] = []

    def make(up: Layout | None, down: Layout | None, leaf: NodeConfig) -> AuthTree:
        if not (tmp_path / "root.key").exists():
            keys(tmp_path)
        made.append(AuthTree(tmp_path, up, down, leaf))
        return made[-1]

    yield make
    for tree in made:
        tree.close()


def drain(bus: can.BusABC) -> list[can.Message]:
    frames = []
    while (frame := bus.recv(0)) is not None:
        frames.append(frame)
    return frames


def refused(status: dict[str, Any]) -> int:
    return sum(status["auth_failures"].values())


# --- energy end to end, a MAC on every frame ------------------------------------------------------


@pytest.mark.parametrize(
    ("up", "down"),
    [(Layout.CLASSIC, Layout.CLASSIC), (Layout.FD, Layout.FD), (Layout.FD, Layout.CLASSIC)],
    ids=["classic", "fd", "fd-up-classic-down"],
)
def test_energy_moves_end_to_end_with_a_mac_on_every_bus(
    make_tree: Any, up: Layout, down: Layout, capsys: pytest.CaptureFixture[str]
) -> None:
    leaf = NodeConfig(
        power=PowerProfile.constant(1.0), return_above=600_000, telemetry_period_us=100_000
    )
    t: AuthTree = make_tree(up, down, leaf)
    # nothing may be refused: a reply later than a 100 ms response timeout (a loaded host) has
    # its command sent again and the copy's answer refused as stale, so wait 1 s on both legs
    patient = ("--response-timeout", "1s")
    t.start_root(*patient)
    t.start_gateway(
        "--target", "1J", "--max-grant", "0.5J", "--return-above", "3.5J",
        *patient, "--upstream-response-timeout", "1s",
    )  # fmt: skip
    granted = t.grant("root", GW, 5_000_000)
    assert granted["outcome"] == "COMMITTED", granted
    # the gateway passes what it holds above 3.5 J back up, grants to the leaf; the leaf
    # spends and returns
    t.wait(lambda: t.status("root")["nodes"][str(GW)]["returns_credited"] >= 1)
    t.wait(lambda: t.status("gw")["nodes"][str(LEAF)]["returns_credited"] >= 1)
    t.wait(lambda: t.status("gw")["nodes"][str(LEAF)]["committed"] >= 3)
    t.wait(lambda: t.leaf.actuator.drawn_uj >= 1_000_000)
    captured_up, captured_down = drain(t.sniff_up), drain(t.sniff_down)
    assert captured_up and all(f.is_fd == (up is Layout.FD) for f in captured_up)
    assert captured_down and all(f.is_fd == (down is Layout.FD) for f in captured_down)
    t.stop("gw")
    t.stop("root")
    t.loop.halt()
    root, gw = t.status("root"), t.status("gw")
    assert root["auth"] == gw["upstream"]["auth"] == up.value and gw["auth"] == down.value
    # below, the gateway runs the compiled core (--core auto) and its frame path with the key:
    # the leaf's answers verified, ruled and answered in C
    assert missing() is None, missing()
    assert (gw["core"], gw["frame_path"]) == ("c", "c") and "frame_path_off" not in gw, gw
    assert gw["frame_path_frames"] >= 3  # at least the leaf's answers of its three commits
    assert refused(root) == refused(gw) == refused(gw["upstream"]) == 0  # nothing refused
    assert gw["upstream"]["credited_uj"] == 5_000_000
    assert root["nodes"][str(GW)]["returns_credited_uj"] > 0  # what it held above 3.5 J
    assert t.leaf.client.state.credited > 0 and t.leaf.status()["returned_uj"] > 0
    books = t.tree()
    assert books.passive, books.as_json()
    # the same books closed by `canergy ledger`
    (t.tmp / "leaf.json").write_text(json.dumps(t.leaf.status()))
    files = [str(t.tmp / name) for name in ("root-status.json", "gw-status.json", "leaf.json")]
    capsys.readouterr()
    assert main(["ledger", "--level", files[0], files[1], "--level", files[1], files[2]]) == 0
    assert "PASSIVE" in capsys.readouterr().out
    # the gateway's state file is sealed with its own master key, whose epoch is recorded
    sealed = json.loads((t.tmp / "gw.json").read_text())
    assert sealed["mac"].startswith("cmac:") and sealed["epoch"] == load_key(t.tmp / "gw.key").epoch
    record = (t.tmp / "gw.key.epochs").read_text()
    assert record.count("\n") == 1 and str((t.tmp / "gw.json").absolute()) in record
    assert (t.tmp / "gw.json").stat().st_mode & 0o777 == 0o600


# --- forgeries and replays on either leg ----------------------------------------------------------


@pytest.mark.parametrize("layout", list(Layout))
def test_keyless_forgeries_and_replays_on_either_leg_move_nothing(
    make_tree: Any, layout: Layout, capsys: pytest.CaptureFixture[str]
) -> None:
    t: AuthTree = make_tree(layout, layout, NodeConfig(telemetry_period_us=100_000))
    t.start_root("--on-intrusion", "stop")
    t.start_gateway()
    assert t.grant("root", GW, 3_000_000)["outcome"] == "COMMITTED"
    assert t.grant("gw", LEAF, 1_000_000)["outcome"] == "COMMITTED"
    t.wait(lambda: t.leaf.client.state.credited == 1_000_000)
    captured_up, captured_down = drain(t.sniff_up), drain(t.sniff_down)
    root, gw = t.status("root"), t.status("gw")
    up_tx, up_seq = (
        root["nodes"][str(GW)]["open_tx"] or 1,
        root["nodes"][str(GW)]["returns_credited"],
    )
    down_tx = gw["nodes"][str(LEAF)]["open_tx"] or 1
    down_seq = gw["nodes"][str(LEAF)]["returns_credited"]
    forgeries = {
        t.rogue_up: [
            Commit(GW, up_tx + 1, 65535),
            Intention(GW, up_tx + 1, 65535, 0),
            Intention(GW, up_tx + 1, 1, 4_000_000),
            Return(GW, up_seq + 1, 65535),
            ReturnAck(GW, up_seq + 1),
        ],
        t.rogue_down: [
            Commit(LEAF, down_tx + 1, 65535),
            Intention(LEAF, down_tx + 1, 65535, 0),
            Return(LEAF, down_seq + 1, 65535),
            ReturnAck(LEAF, down_seq + 1),
        ],
    }
    for bus, msgs in forgeries.items():
        for msg in msgs:
            for shape in (layout, None):  # in the layout's shape with a zero MAC, and plain
                for frame in forged(msg, shape):
                    bus.send(frame)
    for bus, frames in ((t.rogue_up, captured_up), (t.rogue_down, captured_down)):
        for frame in frames:  # every genuine frame so far, replayed
            bus.send(frame)
    t.wait(lambda: refused(t.status("root")) >= 3 and refused(t.status("gw")) >= 3)
    t.wait(lambda: refused(t.status("gw")["upstream"]) >= 3 and t.leaf.intrusions.total >= 3)
    time.sleep(1.0)  # past every response and command timeout
    root, gw = t.status("root"), t.status("gw")
    assert t.threads["root"].is_alive() and not root["stopping"]  # counted, never a reason to stop
    assert gw["upstream"]["refused"]["total"] >= 3 and gw["refused"]["total"] >= 3
    assert root["refused"]["by_node"][str(GW)]["total"] >= 3
    # nothing moved: what each level holds is what it was granted
    assert gw["upstream"]["credited_uj"] == 3_000_000 and gw["upstream"]["usable_uj"] == 0
    assert gw["usable_uj"] == 2_000_000 and gw["nodes"][str(LEAF)]["delivered_uj"] == 1_000_000
    assert root["nodes"][str(GW)]["returns_credited_uj"] == 0
    assert gw["nodes"][str(LEAF)]["returns_credited_uj"] == 0
    assert t.leaf.client.state.credited == 1_000_000 and t.leaf.client.state.usable == 1_000_000
    t.stop("gw")
    t.stop("root")
    assert not t.status("root")["stopped_by_intrusion"]
    books = t.tree()
    assert books.passive, books.as_json()
    _sealed_file_needs_its_key(t, capsys)


def _sealed_file_needs_its_key(t: AuthTree, capsys: pytest.CaptureFixture[str]) -> None:
    """After an authenticated run: the state file is refused without its master key or with
    another one, and new books under a key that kept books are refused (epochs record)."""
    argv = t.gateway_argv()
    without = [a for i, a in enumerate(argv) if a != "--auth" and argv[i - 1] != "--auth"]
    capsys.readouterr()
    assert main(without) == 2
    assert "sealed in authenticated mode" in capsys.readouterr().err
    assert main(["keys", "-o", str(t.tmp / "other.key")]) == 0
    other = [str(t.tmp / "other.key") if a == str(t.tmp / "gw.key") else a for a in argv]
    capsys.readouterr()
    assert main(other) == 2
    assert "the MAC does not match" in capsys.readouterr().err
    (t.tmp / "gw.json").rename(t.tmp / "gw.old.json")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "already began books" in err and "canergy keys --epoch" in err
    assert not (t.tmp / "gw.json").exists()


# --- wrong keys ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("leg", "key", "why"),
    [
        ("--upstream-auth", "root.key", "a master key; upstream the gateway is node 20"),
        ("--upstream-auth", "gw.key", "a master key; upstream the gateway is node 20"),
        ("--upstream-auth", "up/node-021.key", "the key of node 21, but this gateway is node 20"),
        ("--auth", "up/node-020.key", "a node key; downstream the gateway is a supervisor"),
        ("--auth", "down/node-001.key", "a node key; downstream the gateway is a supervisor"),
        ("--auth", "root.key", "the master key --upstream-auth"),
        ("--auth", "open.key", "lets others read it"),
    ],
)
def test_a_key_of_the_wrong_kind_is_refused_on_either_leg(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], leg: str, key: str, why: str
) -> None:
    keys(tmp_path)
    derive(tmp_path / "root.key", 21, tmp_path / "up")
    assert main(["keys", "-o", str(tmp_path / "open.key")]) == 0
    os.chmod(tmp_path / "open.key", 0o644)
    given = {"--upstream-auth": tmp_path / "up" / "node-020.key", "--auth": tmp_path / "gw.key"}
    given[leg] = tmp_path / key
    argv = ["gateway", "--node", str(GW), "--nodes", str(LEAF), "-i", "virtual", "-c", "d"]
    argv += ["--upstream-interface", "virtual", "--upstream-channel", "u"]
    argv += ["--state", str(tmp_path / "gw.json"), "--no-fsync"]
    argv += ["--upstream-auth", str(given["--upstream-auth"]), "--auth", str(given["--auth"])]
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert why in err and f"{leg} {tmp_path / key}" in err, err
    assert err.count("\n") == 1  # one line
    secret = (tmp_path / key).read_text().split("key=")[1].strip()
    assert secret not in err  # a key is never shown
    assert not (tmp_path / "gw.json").exists()  # refused before anything is written
    assert not (tmp_path / "gw.key.epochs").exists()


# --- without a key below: RETURNs held for confirmation, as `canergy supervisor` does -----------


def test_the_return_hold_applies_only_without_a_key_below(tmp_path: Path) -> None:
    keys(tmp_path)
    base = ["gateway", "--node", str(GW), "--nodes", str(LEAF), "--state", str(tmp_path / "s")]
    args = build_parser().parse_args([*base, "--return-hold", "300ms"])
    assert _config(args, None).service.return_hold_us == 300_000
    assert (
        _config(build_parser().parse_args(base), None).service.return_hold_us == 500_000
    )  # default
    assert (
        _config(args, load_key(tmp_path / "gw.key")).service.return_hold_us is None
    )  # a MAC instead


def test_a_keyless_tree_holds_returns_and_refutes_a_forged_one(make_tree: Any) -> None:
    """No key anywhere: the gateway credits its leaf's RETURNs once the leaf confirms them, the
    root (holding RETURNs too) credits the gateway's once the gateway's TELEMETRY confirms them,
    and a forged RETURN in the leaf's name is never credited."""
    leaf = NodeConfig(
        power=PowerProfile.constant(1.0), return_above=600_000, telemetry_period_us=100_000
    )
    t: AuthTree = make_tree(None, None, leaf)
    t.start_root("--return-hold", "300ms")
    t.start_gateway(
        "--target", "1J", "--max-grant", "0.5J", "--return-above", "3.5J", "--return-hold", "300ms"
    )
    assert t.grant("root", GW, 5_000_000)["outcome"] == "COMMITTED"
    t.wait(lambda: t.status("root")["nodes"][str(GW)]["returns_credited"] >= 1)
    t.wait(lambda: t.status("gw")["nodes"][str(LEAF)]["returns_credited"] >= 1)
    seq = t.status("gw")["nodes"][str(LEAF)]["returns_credited"]
    for frame in forged(Return(LEAF, seq + 1, 1), None):  # 1 mJ ahead of the leaf's next one
        t.rogue_down.send(frame)
    t.wait(lambda: t.status("gw")["nodes"][str(LEAF)]["returns_refuted"] >= 1)
    assert t.status("gw")["nodes"][str(LEAF)]["intrusions"] >= 1  # the leaf's report, raised
    t.stop("gw")
    t.stop("root")
    t.loop.halt()
    gw = t.status("gw")
    assert gw["nodes"][str(LEAF)]["returns_credited_uj"] <= t.leaf.status()["returned_uj"]
    assert gw["auth"] is None and gw["upstream"]["auth"] is None
    books = t.tree()
    assert books.passive, books.as_json()
