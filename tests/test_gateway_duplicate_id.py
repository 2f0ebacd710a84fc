"""Two gateways with one id above (review rv3, F5, as tests/test_duplicate_id.py for nodes): each
sees the other's frames in its name on the bus above, counts them and reports. The gateway's
upstream leg keeps the node's gap: it brings its TELEMETRY forward for a frame in its name no
sooner than ``WITNESS_GAP_US`` after its last one, so the pair's rate is bounded, and a forged
RETURN or JOIN in its name is still refuted well inside the supervisor's least hold.

The Python gateway (``Uplink``) runs in virtual time, two of them frame for frame and one with a
supervisor above; the C gateway's leg above (ports/linux/gateway_above.c) in a harness
(tests/support/gateway_above_harness.c: the bus above on a socketpair, time given here).
"""

from __future__ import annotations

import subprocess
from collections.abc import Sequence
from pathlib import Path

import can
import pytest
from support.firmware_build import GATEWAY_PORT
from support.firmware_build import harness as built_harness
from test_c_gateway_port_below import rx
from test_duplicate_id import DURATION_US, LATENCY_US, PERIOD_US, at_the_bound, storm
from test_witness import Wire

from canergy.codec import Codec
from canergy.core import Supervisor, gateway
from canergy.live.gateway.process import GatewayFiles, Uplink, UplinkConfig
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.service import JOIN_HOLD_US, ServiceConfig
from canergy.live.supervisor.witness import (
    RETURN_HOLD_MIN_US,
    WITNESS_GAP_US,
    WITNESS_REPORT_AT,
)
from canergy.messages import Join, Message, Return, Telemetry

CODEC = Codec()
UP = 20
"""The gateways' id above."""


def _uplink(node: int = UP) -> Uplink:
    core = gateway.Gateway(node, (1, 2))
    return Uplink(core, UplinkConfig(telemetry_period_us=PERIOD_US), GatewayFiles(core, None), 0)


class Gateway:
    """One Python gateway's leg above, every frame it sends kept with its time (a ``Board``)."""

    def __init__(self, nonce: int) -> None:
        self.up = _uplink()
        self.up.start_without_books(nonce, 0)
        self.sent: list[tuple[int, Message]] = []

    def _kept(self, out: Sequence[Message], now: int) -> list[Message]:
        self.sent += [(now, m) for m in out]
        return list(out)

    def wakeup(self, now: int) -> list[Message]:
        return self._kept(self.up.on_wakeup(now), now)

    def frame(self, msg: Message, now: int) -> list[Message]:
        """The other gateway's frame: in this one's name, in the direction only it sends."""
        ident, data = CODEC.encode(msg)
        frame = can.Message(arbitration_id=ident, data=data, is_extended_id=True)
        return self._kept(self.up.on_foreign_direction(frame, now), now)

    def next_wakeup(self) -> int:
        due = self.up.next_wakeup()
        assert due is not None
        return due

    def telemetry_times(self) -> list[int]:
        return [t for t, m in self.sent if isinstance(m, Telemetry)]


def test_two_python_gateways_on_one_id_report_at_most_once_a_gap() -> None:
    """Each gateway reports the other's frames as frames in its name, a gap after its own last
    TELEMETRY: the storm runs at its bound (one TELEMETRY per ``WITNESS_GAP_US`` a gateway),
    no faster; without the gap it ran at one frame per ``LATENCY_US`` (4,000/s a gateway)."""
    a, b = Gateway(0x1111), Gateway(0x2222)
    storm(a, b, DURATION_US)
    bound = at_the_bound(a.telemetry_times())
    assert a.up.witnessing.count > bound // 2  # it did see the other's frames
    at_the_bound(b.telemetry_times())
    assert b.up.witnessing.count > bound // 2
    assert len(a.sent) + len(b.sent) <= 3 * bound  # its JOINs besides


def test_the_python_gateways_128th_unreported_frame_is_still_reported_at_once() -> None:
    """The gap does not hold back the report at ``WITNESS_REPORT_AT`` unreported frames."""
    up = _uplink()
    up.on_wakeup(0)  # its boot report: the gap runs until WITNESS_GAP_US
    ident, data = CODEC.encode(Telemetry(UP, 5, 0, 0, 0))
    forged = can.Message(arbitration_id=ident, data=data, is_extended_id=True)
    out = [list(up.on_foreign_direction(forged, 10 + i)) for i in range(WITNESS_REPORT_AT)]
    assert out[:-1] == [[]] * (WITNESS_REPORT_AT - 1)
    ((report,),) = out[-1:]
    assert isinstance(report, Telemetry) and report.witness == WITNESS_REPORT_AT
    assert up.next_wakeup() == 50_000  # its tick: nothing brought forward after the report


class GatewayWire(Wire):
    """``Wire`` with a Python gateway's leg above in the node's place, under the least RETURN
    hold a supervisor accepts (``RETURN_HOLD_MIN_US``)."""

    def __init__(self) -> None:
        config = ServiceConfig(
            return_hold_us=RETURN_HOLD_MIN_US, fsync=False, status_period_us=10**12
        )
        self.service = build_service(Supervisor((1,), 10_000_000), config, 0)
        self.uplink = _uplink(1)
        self.uplink.start_without_books(0x4242, 0)
        self.host = self.uplink  # type: ignore[assignment]
        self.held = []
        self.hold_down = False


def _reported_now() -> tuple[GatewayWire, int]:
    """A gateway admitted above, 1 J committed to it at ``t``: it reports its level at once."""
    w = GatewayWire()
    w.run(0)
    w.run(JOIN_HOLD_US)
    assert not w.uplink.joining
    t = 2 * JOIN_HOLD_US
    w.service.request_grant(1, 1_000_000, lambda reply: None)
    w.run(t)
    assert w.uplink.gateway.down.usable == 1_000_000
    assert w.uplink.early_telemetry == t + WITNESS_GAP_US  # its last report: now
    return w, t


def test_a_forged_return_right_after_the_gateways_report_is_refuted_within_the_hold() -> None:
    """The worst case for the gap: a forged RETURN in the gateway's name and a forged TELEMETRY
    confirming it, sent the very microsecond it reported. Its next TELEMETRY leaves
    ``WITNESS_GAP_US`` later, a tenth of the least hold, and the RETURN is refuted."""
    w, t = _reported_now()
    w.forge(Return(1, 1, 1_000), t)
    w.forge(Telemetry(1, 0, 0, 1, w.uplink.witnessing.reported), t)
    w.run(t + WITNESS_GAP_US - 1)
    assert w.service.intrusions.as_json()["first_at_us"] is None  # within the gap: not yet
    w.run(t + WITNESS_GAP_US)
    assert w.service.intrusions.as_json()["first_at_us"] == t + WITNESS_GAP_US
    assert WITNESS_GAP_US * 10 == RETURN_HOLD_MIN_US
    w.run(t + 10 * RETURN_HOLD_MIN_US)
    status = w.node_status()
    assert status["returns_refuted"] == 1 and status["returns_credited"] == 0
    assert w.uplink.gateway.down.usable == 1_000_000  # nothing taken from it


def test_a_forged_join_right_after_the_gateways_report_writes_nothing_off() -> None:
    """A forged JOIN in the gateway's name the microsecond it reported: refuted a gap later,
    well inside the JOIN's hold; the gateway keeps its books and its budget."""
    w, t = _reported_now()
    w.forge(Join(1, 0x0007), t)
    w.run(t + WITNESS_GAP_US)
    assert w.service.intrusions.as_json()["first_at_us"] == t + WITNESS_GAP_US
    w.run(t + 10 * JOIN_HOLD_US)
    status = w.node_status()
    assert status["admitted"] == 1 and status["written_off"] == 0
    assert not w.uplink.joining and w.uplink.gateway.down.usable == 1_000_000


# --- the C gateway's leg above ------------------------------------------------------------------


@pytest.fixture(scope="module")
def harness(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The harness (the bus above) built under ASan and UBSan."""
    port = ["gateway_above.c", "gateway_below.c", *GATEWAY_PORT]
    return built_harness("gateway_above_harness", tmp_path_factory.mktemp("harness"), port)


def _c_reports(harness: Path, tmp: Path, script: list[str]) -> list[tuple[int, Telemetry]]:
    """The C gateway (node ``UP`` above) run on ``script``: its TELEMETRY above, with times."""
    args = [str(harness), "--node", str(UP), "--nodes", "1-2", "-c", "down"]
    args += ["--upstream-channel", "up", "--nv", str(tmp / "gw.nv")]
    args += ["--telemetry-period", f"{PERIOD_US}us"]
    done = subprocess.run(
        args, input="\n".join(script) + "\n", capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    reports = []
    for line in done.stdout.splitlines():
        _, at, frame = line.split()
        ident, data = frame.split("#")
        msg = CODEC.decode(int(ident, 16), bytes.fromhex(data))
        if isinstance(msg, Telemetry):
            reports.append((int(at), msg))
    return reports


def _forged_telemetry() -> str:
    return rx(Telemetry(UP, 5, 0, 0, 0))


def test_the_c_gateway_answers_a_storm_in_its_name_at_most_once_a_gap(
    harness: Path, tmp_path: Path
) -> None:
    """A twin on its id that answers at once (what each gateway did before the gap): a frame in
    the C gateway's name every ``LATENCY_US`` for 2 s. The gateway reports them a gap after its
    last TELEMETRY, no sooner: at its bound; without the gap it answered every one (8,000)."""
    script = []
    for k in range(DURATION_US // LATENCY_US):
        script += [f"at {1 + LATENCY_US * (k + 1)}", _forged_telemetry()]
    reports = _c_reports(harness, tmp_path, script)
    at_the_bound([t for t, _ in reports])
    assert all(m.witness for _, m in reports[1:])  # each one reports the storm


def test_the_c_gateway_reports_a_gap_after_its_last_and_the_128th_at_once(
    harness: Path, tmp_path: Path
) -> None:
    """A forged frame in its name the microsecond after its boot report: reported exactly
    ``WITNESS_GAP_US`` later (Python's gap, far inside the least hold); then a burst right after
    a report is reported on its ``WITNESS_REPORT_AT``-th frame, not held back by the gap."""
    t = 1 + WITNESS_GAP_US  # its boot report at 1
    script = ["at 2", rx(Return(UP, 1, 1_000)), f"at {t - 1}", f"at {t}"]
    for i in range(WITNESS_REPORT_AT):
        script += [f"at {t + 1 + i}", _forged_telemetry()]
    reports = _c_reports(harness, tmp_path, script)
    assert [(at, m.witness) for at, m in reports] == [
        (1, 0),
        (t, 1),  # the forged RETURN, a gap after the boot report
        (t + WITNESS_REPORT_AT, 1 + WITNESS_REPORT_AT),  # the burst's last frame, at once
    ]
    assert WITNESS_GAP_US <= RETURN_HOLD_MIN_US // 10
