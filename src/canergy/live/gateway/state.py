"""A gateway's non-volatile record: its upstream client record and its downstream supervisor's
books in one JSON file, replaced atomically, so the two roles never disagree after a crash.

The downstream part is a supervisor state file's books (checked as ``state_file`` checks them);
the upstream part is the client record the hardened rules persist. Loading also checks the link
between the roles: ``upstream.spent = downstream.injected - downstream.withdrawn`` and nothing
initial downstream (every joule below came from above). A gateway that was still waiting to be
admitted upstream (``joining``) has no upstream books: it joins again at the next start, never
trusting the blank record. Under the witnessed rules upstream (``upstream_variant``; absent:
hardened) the record also holds whether the pending debit is a draw, and may hold usable energy
not drawn yet.

The file is guarded as a supervisor's: a checksum, and in authenticated mode the keys' ``epoch``
and a MAC under a state key derived for this gateway (context: epoch and its node id upstream).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from canergy.auth.state_key import StateSeal
from canergy.core.gateway import GatewayState, link_gap
from canergy.core.state import ClientState, Outcome, Phase, Session
from canergy.frozen import evolve
from canergy.live.supervisor.state_file import (
    TOP_OPTIONAL,
    FieldChecker,
    StateFileError,
    check_guards,
    read_json,
    saves_seal,
    sealed_text,
    state_json,
    write_private,
)
from canergy.messages import AMOUNT_MAX_MJ, MAX_NODE, MIN_NODE, QUANTUM_UJ

FORMAT = "canergy-gateway-state"
VERSION = 1
_TOP = ("format", "version", "variant", "upstream", "downstream")
_TOP_OPTIONAL = (*TOP_OPTIONAL, "upstream_variant")
_UPSTREAM = (
    "node",
    "usable_uj",
    "credited_uj",
    "spent_uj",
    "last_tx",
    "outcome",
    "return_seq",
    "return_pending_uj",
    "credited_unknown",
    "joining",
)
_UPSTREAM_OPTIONAL = ("pending_draw",)


def gateway_json(state: GatewayState, variant: str, up_variant: str = "hardened") -> dict[str, Any]:
    up = state.up
    draw = {"pending_draw": int(up.pending_draw)} if up_variant == "witnessed" else {}
    above = {"upstream_variant": up_variant} if up_variant != "hardened" else {}
    return {
        "format": FORMAT,
        "version": VERSION,
        "variant": variant,
        **above,
        "upstream": {
            "node": up.node,
            "usable_uj": up.usable,
            "credited_uj": up.credited,
            "spent_uj": up.spent,
            "last_tx": up.last_tx,
            "outcome": up.outcome.name,
            "return_seq": up.return_seq,
            "return_pending_uj": up.return_pending,
            "credited_unknown": int(up.credited_unknown),
            "joining": int(up.phase is Phase.JOINING),
            **draw,
        },
        "downstream": state_json(state.down, variant),
    }


def save_gateway(
    path: Path,
    state: GatewayState,
    variant: str,
    *,
    fsync: bool = True,
    seal: StateSeal | None = None,
    up_variant: str = "hardened",
) -> None:
    """Write the record (0600); ``seal``: by default the one ``keep_books`` set for ``path``."""
    seal = seal if seal is not None else saves_seal(path)
    text = sealed_text(gateway_json(state, variant, up_variant), seal)
    write_private(path, text, fsync=fsync)


def load_gateway(
    path: Path,
    variant: str,
    node: int,
    nodes: tuple[int, ...],
    *,
    accept_edited: bool = False,
    on_edited: Callable[[str], None] | None = None,
    seal: StateSeal | None = None,
    up_variant: str = "hardened",
) -> GatewayState:
    """Read and check ``path`` for gateway ``node`` over ``nodes``; refused naming the field.
    ``seal``: authenticated mode (derived for ``node``). A missing or wrong checksum or MAC is
    taken only with ``accept_edited`` (``on_edited`` hears it); another epoch never."""
    data = read_json(path)
    check = FieldChecker(path)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise StateFileError(f"{path}: not a {FORMAT} file")
    check.fields(data, "", _TOP, optional=_TOP_OPTIONAL)
    if type(data["version"]) is not int or data["version"] != VERSION:
        check.refuse("version", f"{data['version']!r} is not {VERSION}")
    if data["variant"] != variant:
        raise StateFileError(f"{path}: written by variant {data['variant']!r}, not {variant!r}")
    above = data.get("upstream_variant", "hardened")
    if above != up_variant:
        raise StateFileError(f"{path}: written by upstream variant {above!r}, not {up_variant!r}")
    check_guards(path, data, seal, accept_edited, on_edited)
    up = _upstream(check, data["upstream"], node, witnessed=up_variant == "witnessed")
    down = check.books(data["downstream"], variant)
    extra = sorted({s.node for s in down.sessions} - set(nodes))
    if extra:
        raise StateFileError(
            f"{path} holds books for downstream node(s) {extra} not in --nodes; add them"
        )
    if down.initial:
        check.refuse("downstream.initial_uj", "a gateway's budget all comes from upstream: 0")
    if (gap := link_gap(up, down)) != 0:
        check.refuse(
            "upstream.spent_uj",
            f"the roles disagree by {gap} µJ: upstream spent must equal downstream injected "
            "minus withdrawn",
        )
    by_node = {s.node: s for s in down.sessions}
    down = evolve(down, sessions=tuple(by_node.get(n, Session(n)) for n in sorted(nodes)))
    return GatewayState(up, down)


def _upstream(check: FieldChecker, raw: object, node: int, *, witnessed: bool) -> ClientState:
    """The upstream record. One never admitted (blank: what a new client holds) is JOINING: the
    gateway joins again rather than trust it, whatever its ``joining`` field says. Witnessed:
    what is usable waits for its draw, and the pending debit may be one."""
    v = check.fields(raw, "upstream", _UPSTREAM, optional=_UPSTREAM_OPTIONAL if witnessed else ())
    found = check.integer(v, "upstream", "node", MAX_NODE)
    if found != node or found < MIN_NODE:
        check.refuse("upstream.node", f"{found}, but this gateway is node {node} (--node)")
    outcome = Outcome[check.name(v, "upstream", "outcome", (o.name for o in Outcome))]
    usable = check.integer(v, "upstream", "usable_uj")
    if usable and not witnessed:
        check.refuse("upstream.usable_uj", "a gateway forwards what it is credited: 0")
    draw = bool(check.integer(v, "upstream", "pending_draw", 1)) if "pending_draw" in v else False
    pending = check.integer(v, "upstream", "return_pending_uj", AMOUNT_MAX_MJ * QUANTUM_UJ)
    if pending % QUANTUM_UJ:
        check.refuse("upstream.return_pending_uj", f"{pending} µJ is not a whole number of mJ")
    up = ClientState(
        node,
        usable=usable,
        credited=check.integer(v, "upstream", "credited_uj"),
        spent=check.integer(v, "upstream", "spent_uj"),
        last_tx=check.counter(v, "upstream", "last_tx"),
        outcome=outcome,
        return_seq=check.counter(v, "upstream", "return_seq"),
        return_pending=pending,
        credited_unknown=bool(check.integer(v, "upstream", "credited_unknown", 1)),
        pending_draw=draw,
    )
    if pending and not up.return_seq:
        check.refuse("upstream.return_pending_uj", "a return pending with return_seq 0")
    if draw and not pending:
        check.refuse("upstream.pending_draw", "a draw of nothing pending")
    joining = check.integer(v, "upstream", "joining", 1)
    if joining and up != ClientState(node):
        check.refuse("upstream.joining", "a gateway that is joining has no upstream books yet")
    return evolve(up, phase=Phase.JOINING) if up == ClientState(node) else up
