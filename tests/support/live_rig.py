"""An in-process bench: a supervisor service and firmware node hosts, each on its own python-can
``virtual`` bus connection and its own loop thread (the pytest plugin's ``Loop``, re-exported
here), on the wall clock (timeouts are generous)."""

from __future__ import annotations

import random
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path

import can

from canergy.codec import Codec
from canergy.core import ClientState, Supervisor, Timing
from canergy.faults import FaultInjector, FaultProfile
from canergy.ledger import Ledger, ledger
from canergy.live.runtime import BusCounters, BusRuntime, monotonic_us
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.policy import Limits, TopUp
from canergy.live.supervisor.service import ServiceConfig, SupervisorService
from canergy.live.supervisor.state_file import load_state
from canergy.live.transports.faulty_bus import FaultyBus
from canergy.messages import Direction
from canergy.testing.run import Loop, until
from canergy.units import UJ_PER_J
from firmware_model.actuator import PowerProfile
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

__all__ = ["TIMING", "Loop", "Rig"]

TIMING = Timing(response_timeout_us=100_000, retries=3, command_timeout_us=200_000)


class Rig:
    def __init__(
        self,
        tmp: Path,
        nodes: Sequence[int],
        *,
        initial: int = 1000 * UJ_PER_J,
        target: int = UJ_PER_J,
        max_grant: int = UJ_PER_J // 2,
        power_w: float = 0.0,
        faults: FaultProfile | None = None,
        seed: int = 0,
        return_above: int | None = None,
    ) -> None:
        self.tmp, self.nodes, self.initial = tmp, tuple(nodes), initial
        self.target, self.max_grant, self.power_w = target, max_grant, power_w
        self.faults, self.rng = faults, random.Random(seed)
        self.return_above = return_above
        self.channel = f"rig-{uuid.uuid4().hex}"
        self.codec = Codec()
        self.service: SupervisorService | None = None
        self.sup_loop: Loop | None = None
        self.hosts: list[tuple[NodeHost, Loop]] = []
        self.retired: dict[int, FirmwareNode] = {}
        self.started_from: dict[int, ClientState] = {}
        """Each node's state as its last start took it from NV, before its loop ran."""

    # -- parts -------------------------------------------------------------------------------
    def _bus(self, filters: list[dict[str, int | bool]]) -> can.BusABC:
        bus = can.Bus(interface="virtual", channel=self.channel, can_filters=filters)
        if self.faults is None:
            return bus
        injector = FaultInjector(self.faults, random.Random(self.rng.random()))
        return FaultyBus(bus, injector)

    def start_supervisor(self) -> SupervisorService:
        state_path = self.tmp / "supervisor.json"
        state = load_state(state_path, "hardened", self.nodes) if state_path.exists() else None
        core = Supervisor(self.nodes, self.initial, timing=TIMING, state=state)
        now = monotonic_us()
        if state is not None:
            core.power_loss(now)
        config = ServiceConfig(
            policy=TopUp(self.target),
            limits=Limits(max_grant=self.max_grant),
            state_path=state_path,
            status_path=self.tmp / "supervisor-status.json",
            lost_after_us=10_000_000,
            fsync=False,
        )
        counters = BusCounters()
        self.service = build_service(core, config, now, bus_counters=counters)
        runtime = BusRuntime(
            self._bus(self.codec.supervisor_filters()),
            self.service,
            codec=self.codec,
            receives=Direction.TO_SUPERVISOR,
            counters=counters,
        )
        self.sup_loop = Loop(runtime)
        return self.service

    def start_clients(self, nodes: Sequence[int] | None = None, **nv: int) -> NodeHost:
        ids = tuple(nodes or self.nodes)
        now = monotonic_us()
        config = NodeConfig(
            power=PowerProfile.constant(self.power_w),
            timing=TIMING,
            telemetry_period_us=300_000,
            return_above=self.return_above,
        )
        host = NodeHost(
            [
                FirmwareNode(
                    n, NvStore(self.tmp / f"node-{n}.nv", n, fsync=False, **nv), config, now
                )
                for n in ids
            ]
        )
        self.started_from.update((n, node.client.state) for n, node in host.nodes.items())
        filters = [f for n in ids for f in self.codec.client_filters(n)]
        runtime = BusRuntime(
            self._bus(filters), host, codec=self.codec, receives=Direction.TO_CLIENT
        )
        self.hosts.append((host, Loop(runtime)))
        return host

    # -- control -----------------------------------------------------------------------------
    def wait(self, condition: Callable[[], bool], timeout_s: float = 60.0) -> None:
        def holds() -> bool:
            self.raise_loop_errors()
            return condition()

        until(holds, "the condition", timeout_s)

    def raise_loop_errors(self) -> None:
        loops = [loop for _, loop in self.hosts] + ([self.sup_loop] if self.sup_loop else [])
        for loop in loops:
            if loop.error is not None:
                raise AssertionError(f"a loop died: {loop.error!r}") from loop.error

    def power_loss_supervisor(self) -> None:
        assert self.sup_loop is not None
        self.sup_loop.halt()
        self.sup_loop = None

    def power_loss_clients(self, host: NodeHost) -> None:
        for h, loop in list(self.hosts):
            if h is host:
                loop.halt()
                self.hosts.remove((h, loop))
                for n in h.nodes.values():  # what survives a power loss is the NV record
                    n.client.state = n.nv.load() or ClientState(n.node)
                self.retired.update(h.nodes)

    def settle(self, timeout_s: float = 60.0) -> None:
        """Stop the supervisor as SIGTERM does and wait until its books are closed."""
        service, loop = self.service, self.sup_loop
        assert service is not None and loop is not None
        service.stop(monotonic_us())
        self.wait(lambda: service.finished(monotonic_us()), timeout_s)
        loop.halt()
        self.sup_loop = None

    def close(self) -> None:
        if self.sup_loop is not None:
            self.sup_loop.halt()
        for _, loop in self.hosts:
            loop.halt()
        self.hosts.clear()

    # -- books -------------------------------------------------------------------------------
    def client_nodes(self) -> dict[int, FirmwareNode]:
        nodes = dict(self.retired)
        for host, _ in self.hosts:
            nodes.update(host.nodes)
        return nodes

    def ledger(self) -> Ledger:
        assert self.service is not None
        return ledger(
            self.service.core.state, [n.client.state for n in self.client_nodes().values()]
        )

    def committed(self, node: int) -> int:
        assert self.service is not None
        return self.service.nodes[node].committed
