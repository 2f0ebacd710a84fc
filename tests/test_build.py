"""The supervisor's one front door, ``canergy.live.supervisor.build``: the rule that nothing else
puts a supervisor together or patches one once built, and what the builder hands over."""

from __future__ import annotations

import re
import uuid
from pathlib import Path
from typing import Any

import can
import pytest

from canergy.codec import Codec
from canergy.live.canopen.cia402_host import HostBeat
from canergy.live.supervisor.build import CoreConfig, SupervisorConfig, build_supervisor
from canergy.live.supervisor.service import ServiceConfig
from canergy.messages import Telemetry

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted(
    [*(ROOT / "src" / "canergy").rglob("*.py"), *(ROOT / "firmware_model").rglob("*.py")]
)
TESTS = sorted([*(ROOT / "tests").rglob("*.py"), *(ROOT / "examples").rglob("*.py")])
BUILDER = ROOT / "src" / "canergy" / "live" / "supervisor" / "build.py"
J = 1_000_000


def _where(pattern: str, skip: Path | None = None, paths: list[Path] = SOURCES) -> list[str]:
    found = []
    for path in paths:
        if path == skip:
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(pattern, line) and not line.lstrip().startswith(("class ", "#")):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    return found


def test_only_the_builder_puts_a_supervisor_together() -> None:
    """The rule: in canergy and the firmware model, the supervisor service, the gateway's
    downstream service and the guarded devices in front of them are made in
    ``canergy.live.supervisor.build`` and nowhere else (unit tests of the parts may make them)."""
    made = r"\b(SupervisorService|DownstreamService|GuardedSupervisor|GuardedDevices)\("
    assert _where(made, skip=BUILDER) == []


def test_nothing_is_assigned_onto_a_built_supervisor() -> None:
    """The rule: a built service, its bus loop and the gateway's uplink get every
    collaborator through their constructors; no code outside them assigns one afterwards (a
    loop's ``max_batch`` neither: ``SupervisorConfig.max_batch``; nor its clock), in the tests
    and examples either (a test that must watch a part patches its class, for that test)."""
    patched = (
        r"\b(service|runtime|uplink|supervisor|guarded|node_loop|loop)\.\w+(\[[^]]*\])?\s*=[^=]"
    )
    assert _where(patched) == []
    assert _where(patched, paths=TESTS) == []


def test_a_core_s_parts_are_declared_not_discovered() -> None:
    """The rule: what the service asks of a core (its tables in C, the nodes a start waits for,
    its frame path) is declared in ``SupervisorCore``, None where a core has none in C; nothing
    looks it up by name on the core."""
    assert _where(r"getattr\(\s*(self\.)?_?core\b") == []


def test_the_service_makes_none_of_its_parts() -> None:
    """The rule: every part of the service (the watch, the held JOINs, the frame path, the
    status report, the loop pass, the stop they share) is made by the builder and handed over
    in ``ServiceParts``; none is made in ``service.py`` nor calls back into the service."""
    service = ROOT / "src" / "canergy" / "live" / "supervisor" / "service.py"
    parts = r"\b(BusWatch|JoinHold|CoreFramePath|StatusReport|Pass|Stopping|ReturnGate|Ledger)\("
    assert _where(parts, paths=[service]) == []
    assert _where(r"\b(admit|stop|answered|held|telemetry|join_held|decoded)=self\.") == []


def test_a_stop_the_watch_asks_for_answers_the_requests_that_wait() -> None:
    """Evidence under ``--on-intrusion stop`` stops the supervisor through the ``Stopping`` its
    parts share: nothing more begins, and the one-shot grants still queued are answered at the
    next tick with why (before, the watch called the service's ``stop``)."""
    from canergy.core import Supervisor
    from canergy.live.supervisor.build import build_service

    config = ServiceConfig(stop_on_intrusion=True, fsync=False, status_period_us=10**12)
    service = build_service(Supervisor((3,), 10 * J), config, 0)
    replies: list[dict[str, Any]] = []
    service.request_grant(3, J, replies.append)  # waits: node 3 was never heard
    service.authentic_intrusion(3, "a frame", "authentic evidence", 10)
    assert service.stopping and service.stopped_by_intrusion and replies == []
    assert service.stop_deadline == 10 + config.stop_timeout_us
    service.on_wakeup(config.tick_us)
    assert replies == [
        {"node": 3, "error": "node never heard from (or still joining): nothing granted"}
    ]
    assert service.status()["stopping"] and service.finished(11)  # nothing open


class _Link:
    def __init__(self) -> None:
        self.closed = False

    def close(self) -> None:
        self.closed = True

    def status(self) -> dict[str, str]:
        return {"link": "quiet"}


class _Drives:
    """A CiA 402 group whose one drive's guard is never alive and whose link notes a close."""

    nodes = (9,)

    def __init__(self) -> None:
        self.link = _Link()

    def open(self, network: Any, now: int, clock: Any) -> tuple[dict[int, Any], HostBeat, None]:
        class Guard:
            halted = True

            def alive(self, now: int) -> bool:
                return False

            def status(self, now: int) -> dict[str, str]:
                return {"guard": "dead"}

        return {9: (Guard(), self.link)}, HostBeat(), None


def test_a_build_that_fails_leaves_no_guarded_drive_open(tmp_path: Path) -> None:
    """The drives are opened before the service (it takes their liveness and status): a service
    that refuses its configuration closes them, and the control socket, on the way out."""
    drives = _Drives()
    config = SupervisorConfig(
        core=CoreConfig((9,), J),
        service=ServiceConfig(listen_only=True, inject_uj=J),  # refused by the service
        control_path=tmp_path / "ctl",
        cia402=drives,
    )
    with pytest.raises(ValueError, match="--inject"):
        build_supervisor(config, clock=lambda: 0)
    assert drives.link.closed
    assert not (tmp_path / "ctl").exists()


def test_the_service_has_the_guarded_drives_liveness_and_status() -> None:
    """Once assigned by the guarded host onto the service it was given, now handed to the
    service's constructor: a drive whose guard is not alive is granted nothing, and the
    status shows the drives."""
    service = build_supervisor(
        SupervisorConfig(core=CoreConfig((1, 9), J), cia402=_Drives()), clock=lambda: 0
    ).service
    assert service.liveness is not None
    assert (service.liveness(9, 0), service.liveness(1, 0)) == (False, True)
    assert service.status()["cia402"]["drives"] == {"9": {"guard": "dead", "link": "quiet"}}


def test_the_service_shows_the_counters_its_bus_loop_counts_in() -> None:
    """Once assigned onto the service after its bus loop was made, now one object both are
    given: a frame the loop receives is in the service's status."""
    status, same = _one_telemetry(SupervisorConfig(core=CoreConfig((1,), J)))
    assert status["frames_received"] == 1 and same


def _one_telemetry(config: SupervisorConfig) -> tuple[dict[str, Any], bool]:
    """Build ``config`` on a virtual bus, send it node 1's TELEMETRY, poll until it counts the
    frame: its status, and whether its loop and its service count in one object."""
    channel = f"build-{uuid.uuid4().hex}"
    bus, node = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    try:
        built = build_supervisor(config, [bus])
        arbitration_id, data = Codec().encode(Telemetry(1, 5, 0))
        node.send(can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=True))
        for _ in range(100):
            built.loop.poll(0.01)
            if built.service.status()["frames_received"]:
                break
        status = built.service.status()
        same = built.runtimes[0].counters is built.service.bus_counters
        built.close()
    finally:
        bus.shutdown()
        node.shutdown()
    return status, same


def test_several_buses_take_no_canopen_nor_guarded_drives() -> None:
    """They work on one bus: a configuration that asks for them over several is refused, not
    served without them."""
    config = SupervisorConfig(
        core=CoreConfig((1 << 8 | 1, 9), J),
        service=ServiceConfig(bus_names=("a", "b")),
        cia402=_Drives(),
    )
    with pytest.raises(ValueError, match="one bus"):
        build_supervisor(config, [object(), object()])  # type: ignore[list-item]


def _keyed(keys: tuple[Any, ...], bus_keys: tuple[Any, ...], tmp: Path) -> SupervisorConfig:
    """Node 1 on buses a and b, node 2 on b; the books at ``tmp``/s.json, a control socket."""
    from canergy.live.supervisor.build import AuthConfig

    sessions = (1, 1 << 8 | 1, 1 << 8 | 2)
    return SupervisorConfig(
        core=CoreConfig(sessions, J, state_path=tmp / "s.json"),
        service=ServiceConfig(bus_names=("a", "b"), state_path=tmp / "s.json", fsync=False),
        auth=AuthConfig(keys[0], bus_keys=bus_keys),
        control_path=tmp / "c.sock",
    )


def test_a_node_id_on_two_buses_under_one_key_is_refused_by_the_builder(tmp_path: Path) -> None:
    """A node's key comes from the master key and its id alone: with one key for both buses
    node 1's two sessions would share it (a frame of a/1 would verify as b/1). Every caller of
    the builder is refused, with the core opened from the config or handed over, before the
    books are claimed or the control socket bound; with a key per bus (``bus_keys``) it builds.
    """
    from canergy.auth.keys import Key, new_master
    from canergy.ccore.supervisor import make_supervisor

    one = new_master(1)
    same = Key("master", 1, one.secret)  # another key object, the same key
    buses = [can.Bus(interface="virtual", channel=f"keys-{uuid.uuid4().hex}") for _ in "ab"]
    try:
        for bus_keys in ((), (one, same)):
            config = _keyed((one,), bus_keys, tmp_path)
            with pytest.raises(ValueError, match="node 1 is on bus a and on bus b under the same"):
                build_supervisor(config, buses)
            assert config.core is not None
            core = make_supervisor("python", config.core.nodes, J, buses=True)
            with pytest.raises(ValueError, match="node 1 is on bus a and on bus b under the same"):
                build_supervisor(config, buses, core=core)
            assert not list(tmp_path.iterdir())  # no books claimed, no socket bound
        with pytest.raises(ValueError, match="1 bus keys for 2 buses"):
            build_supervisor(_keyed((one,), (one,), tmp_path), buses)
        built = build_supervisor(_keyed((one,), (one, new_master(1)), tmp_path), buses)
        assert set(built.service.status()["nodes"]) == {"a/1", "b/1", "b/2"}
        left, right = (r.auth.key_for(1) for r in built.runtimes if r.auth is not None)
        assert left == one.node_key(1) != right  # each bus's frames under its own key
        built.close()
    finally:
        for bus in buses:
            bus.shutdown()


def _one_answer(config: SupervisorConfig, layout: Any) -> tuple[dict[str, Any], list[Any]]:
    """Build ``config`` (authenticated, ``layout``) on a virtual bus; node 1 reports its level,
    is granted 1 J and acknowledges it, each frame under its key: the status, and what the
    node heard verified (INTENTION, then COMMIT)."""
    from canergy.auth.frames import FrameAuth, expected_freshness
    from canergy.auth.keys import frame_auth_keys
    from canergy.messages import Ack, Direction

    assert config.auth is not None
    keys, codec = frame_auth_keys(config.auth.key), Codec()
    channel = f"build-{uuid.uuid4().hex}"
    bus, node = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    heard: list[Any] = []
    try:
        built = build_supervisor(config, [bus])

        def send(msg: Any, fv: int) -> None:
            for frame in FrameAuth(codec, layout, keys, Direction.TO_CLIENT, lambda m: fv).frames(
                msg
            ):
                node.send(frame)

        def poll(until: Any) -> None:
            check = FrameAuth(
                codec, layout, keys, Direction.TO_CLIENT, lambda m: expected_freshness(m, 1, 0)
            )
            for _ in range(100):
                built.loop.poll(0.01)
                while (frame := node.recv(0)) is not None:
                    verdict = check.accept(frame)
                    if verdict.failure is None and verdict.message is not None:
                        heard.append(verdict.message)
                if until():
                    return

        send(Telemetry(1, 5, 0), 0)
        poll(lambda: built.service.status()["frames_received"])
        built.service.request_grant(1, J, lambda reply: None)
        poll(lambda: heard)
        send(Ack(1, 1), 1)
        poll(lambda: len(heard) > 1)
        status = built.service.status()
        built.close()
    finally:
        bus.shutdown()
        node.shutdown()
    return status, heard


@pytest.mark.parametrize("auth", [None, "fd"])
def test_the_loop_is_handed_the_python_cores_frame_path_and_the_status_says_so(
    auth: str | None,
) -> None:
    """On the Python core the builder hands the loop that core's frame path
    (``canergy.core.frame_answers``, which takes the answers: tests/test_frame_answers.py); with
    a key the bus loop verifies and decodes each frame instead, and the status says why."""
    from canergy.auth.frames import Layout
    from canergy.auth.keys import new_master
    from canergy.live.supervisor.build import AuthConfig

    config = SupervisorConfig(
        core=CoreConfig((1,), J, kind="python"),
        auth=None if auth is None else AuthConfig(new_master(1), fd=True),
    )
    status = _one_telemetry(config)[0] if auth is None else _one_answer(config, Layout(auth))[0]
    assert (status["core"], status["frame_path"]) == ("python", "python")
    if auth is None:
        assert "frame_path_off" not in status
    else:
        assert status["frame_path_off"] == "with a key the bus loop verifies and decodes each frame"


@pytest.mark.parametrize(
    ("auth", "listen_only", "path", "off"),
    [
        (None, False, "c", None),
        ("fd", False, "c", None),
        ("classic", False, "c", None),
        (None, True, "python", "--listen-only"),
    ],
)
def test_the_loop_is_handed_the_compiled_cores_frame_path_and_the_status_says_so(
    auth: str | None, listen_only: bool, path: str, off: str | None
) -> None:
    """The frame path is declared: on the compiled core the builder hands the loop its frame
    path, and the status says which path runs and, where C's cannot, why (listen-only). A
    genuine TELEMETRY (without a key) or ACK (with one, either layout: verified, answered and
    its COMMIT protected in C) then goes through C, or does not."""
    from canergy.auth.frames import Layout
    from canergy.auth.keys import new_master
    from canergy.ccore.supervisor import missing
    from canergy.live.supervisor.build import AuthConfig
    from canergy.messages import Commit, Intention

    if missing() is not None:
        pytest.fail(f"the compiled core is not built: {missing()}")
    config = SupervisorConfig(
        core=CoreConfig((1,), J, kind="c", keep_books=not listen_only),
        service=ServiceConfig(listen_only=listen_only),
        auth=None if auth is None else AuthConfig(new_master(1), fd=auth == "fd"),
    )
    if auth is None:
        status, _ = _one_telemetry(config)
    else:
        status, heard = _one_answer(config, Layout(auth))
        assert heard == [Intention(1, 1, 1_000, 0), Commit(1, 1, 1_000)]
        assert status["auth"] == auth and not status["auth_failures"]
    assert status["core"] == "c" and status["frame_path"] == path
    assert status["frame_path_frames"] == (1 if path == "c" else 0)
    if off is None:
        assert "frame_path_off" not in status
    else:
        assert status["frame_path_off"].startswith(off)
