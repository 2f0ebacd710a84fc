"""The supervisor's non-volatile record as a JSON file, replaced atomically on every change.

Only what the core marks persistent is kept: budgets, and per node the transaction number,
phase, reservation, decision, delivered count and return counters. Retry counts and deadlines
are volatile; on load every session restarts through the rules' ``power_loss``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from canergy.core.state import Decision, Phase, Session, SupervisorState
from canergy.live.atomic import write_atomic

FORMAT = "canergy-supervisor-state"
VERSION = 1


class StateFileError(ValueError):
    """The state file is unreadable or does not match the command line."""


def state_json(state: SupervisorState, variant: str) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "version": VERSION,
        "variant": variant,
        "initial_uj": state.initial,
        "usable_uj": state.usable,
        "injected_uj": state.injected,
        "sessions": {
            str(s.node): {
                "phase": s.phase.name,
                "tx": s.tx,
                "reserved_uj": s.reserved,
                "delivered_uj": s.delivered,
                "decision": s.decision.name,
                "returns_credited": s.returns_credited,
                "returned_uj": s.returned,
            }
            for s in state.sessions
        },
    }


def save_state(path: Path, state: SupervisorState, variant: str, *, fsync: bool = True) -> None:
    text = json.dumps(state_json(state, variant), separators=(",", ":"))  # C encoder: fast
    write_atomic(path, text.encode() + b"\n", fsync=fsync)


def load_state(path: Path, variant: str, nodes: tuple[int, ...]) -> SupervisorState:
    """Read ``path``; the file's nodes must all be in ``nodes`` (new nodes get fresh sessions)."""
    try:
        data = json.loads(path.read_text())
        if data.get("format") != FORMAT or data.get("version") != VERSION:
            raise StateFileError(f"{path}: not a {FORMAT} v{VERSION} file")
        if data["variant"] != variant:
            raise StateFileError(f"{path}: written by variant {data['variant']!r}, not {variant!r}")
        sessions = {int(k): _session(int(k), v) for k, v in data["sessions"].items()}
        state = SupervisorState(
            int(data["initial_uj"]), int(data["usable_uj"]), int(data["injected_uj"])
        )
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        if isinstance(exc, StateFileError):
            raise
        raise StateFileError(f"{path}: unreadable state file ({exc})") from exc
    extra = sorted(set(sessions) - set(nodes))
    if extra:
        raise StateFileError(
            f"{path} holds open books for node(s) {extra} not in --nodes; add them to --nodes"
        )
    merged = tuple(sessions.get(n, Session(n)) for n in sorted(nodes))
    return SupervisorState(state.initial, state.usable, state.injected, merged)


def _session(node: int, v: dict[str, Any]) -> Session:
    return Session(
        node,
        phase=Phase[v["phase"]],
        tx=int(v["tx"]),
        reserved=int(v["reserved_uj"]),
        delivered=int(v["delivered_uj"]),
        decision=Decision[v["decision"]],
        returns_credited=int(v["returns_credited"]),
        returned=int(v["returned_uj"]),
    )
