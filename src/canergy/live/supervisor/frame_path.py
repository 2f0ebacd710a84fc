"""The core's frame path: frames the bus loop has not decoded, taken in one call of the core.

``CoreFramePath`` asks the core for each bus's path (``SupervisorCore.answer_on``: the compiled
core's, without a key or with one in the FD or the classic layout, or the Python core's,
``canergy.core.frame_answers``, without a key) and runs it per frame: the frames the core
encoded are held in the loop pass (``Pass``), and what it did is returned (``Taken``) for the
service to record. Frames are taken only inside a pass, where everything the service decides is
held until the pass ends and the books are written. It calls nothing of the service: the builder
makes it, with the pass and the ``Stopping`` the service shares.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any, cast

import can

from canergy.auth.frames import MAC_TYPE, FrameAuth, Layout
from canergy.ccore.calls import Answer, AuthAnswer, AuthPair, EncodedBegin
from canergy.core.supervisor import BUS_SHIFT, SupervisorCore
from canergy.live.runtime import Outgoing, RawFrame
from canergy.live.supervisor.stopping import Stopping
from canergy.messages import Direction, MsgType

_MAC_TO_SUPERVISOR = MAC_TYPE[Direction.TO_SUPERVISOR]
_ANSWERS = frozenset((MsgType.ACK, MsgType.COMMITTED, MsgType.ABORTED))
"""What the compiled core's frame path takes with a key: a node's answers."""

ANSWERED, HELD, TELEMETRY, JOIN_HELD, DECODED = range(5)
Taken = tuple[int, int, Any, int]
"""What the core took of a frame (said here of C; the Python core's path gives only
``ANSWERED``), for the service: (what, the node's session key, payload, verdict).
``ANSWERED``: an answer the rules took, payload the core's actions (its frames already held in
the pass). ``HELD``: a RETURN the witness in C held, payload the RETURN, verdict the witness's.
``TELEMETRY``: a TELEMETRY the tables in C took, payload the message, verdict the table's bits
with what the witness and the held JOINs found shifted left by 8. ``JOIN_HELD``: a JOIN held in
C. ``DECODED``: a message only decoded in C (a RETURN beyond the books, a JOIN or a DEBIT),
payload the message, for the usual path."""
FastFrame = Callable[[can.Message, int], "Taken | None"]
"""A bus loop's frame through the core's path: what the core took, or None (the usual path)."""


@dataclass(slots=True)
class Pass:
    """The bus loop's passes, shared by the service and its frame path: how deep they nest and
    the frames held until the outermost one ends."""

    depth: int = 0
    held: list[Outgoing] = field(default_factory=list)


class CoreFramePath:
    """The core's frame path for the service's bus loops (``frame_path``)."""

    def __init__(
        self, core: SupervisorCore, buses: int, listen_only: bool, passes: Pass, stopping: Stopping
    ) -> None:
        """``core``: the service's; ``buses``: how many the service serves; ``passes`` and
        ``stopping``: the service's (shared, never called)."""
        self._core: Any = core
        """The compiled core's calls beyond ``SupervisorCore`` (``begin_encoded``, with a key
        ``auth_answer_on``) are asked of it only when it is the compiled core."""
        self.core = core.implementation
        """Whose path runs when one does: "c" or "python"."""
        compiled = self.core == "c"
        self._buses = buses
        self._listen_only = listen_only
        self._pass = passes
        self._stopping = stopping
        """Once the service stops, C aborts what it would commit."""
        self._answer_on = core.answer_on
        self._answer = self._answer_on(0)
        """Bus 0's path without a key (``fast_frame``)."""
        self._answers: dict[int, Answer] = {0: self._answer}
        """Over several buses: each bus's (``frame_path(bus=)``), by bus index."""
        verdicts: tuple[int, int] = cast(Any, core).verdicts if compiled else (0, 0)
        self._held_bit, self._join_bit = verdicts
        """The verdict bits of a RETURN the witness in C held and of a JOIN held in C
        (``CompiledSupervisor.verdicts``, canergy/host.h; none in Python)."""
        self._path: tuple[str, str | None] = ("python", "no bus loop asked for it")
        """Which frame path runs ("python" also where the bus loop decodes), and why not the
        core's."""
        self.frames = 0
        """Frames the core's path took. In C: an answer or a RETURN whole (decode, rules,
        encode), a TELEMETRY (its tables), a RETURN held or a JOIN held, in C; a RETURN beyond
        the books or a DEBIT decoded in C and then handled as usual. With a key in the classic
        layout an answer counts once (its message and its MAC frame). In Python: an answer
        whole (the bus loop decodes the rest with the same codec, as ever)."""
        self._auth_answer: AuthAnswer | None = None
        self._auth_pair: AuthPair | None = None
        self._frame_auth: FrameAuth | None = None
        """Bus 0's path with a key (FD or classic layout) and its bus loop's ``FrameAuth``,
        where what C verified is noted."""
        self._auth_answers: dict[int, AuthAnswer] = {}
        self._auth_pairs: dict[int, AuthPair] = {}
        self._frame_auths: dict[int, FrameAuth] = {}
        """With a key, by bus index (bus 0's also above)."""
        self.begin_encoded: EncodedBegin | None = None
        """The compiled core's ``begin`` with its frame as C encoded it, once a bus loop took
        the path: an INTENTION begun in a pass then leaves as C's bytes (with a key, protected
        in C, once every bus's loop has asked)."""
        self.begin_fd = False
        """With a key in the FD layout the INTENTION ``begin_encoded`` gives is an FD frame."""

    def status(self) -> dict[str, Any]:
        """Which path runs, why not the core's, and how many frames the core's took."""
        path, off = self._path
        return {
            "frame_path": path,
            **({} if off is None else {"frame_path_off": off}),
            "frame_path_frames": self.frames,
        }

    def frame_path(
        self, off: str | None = None, auth: FrameAuth | None = None, bus: int = 0
    ) -> FastFrame | None:
        """``SupervisorService.frame_path``: this path for bus ``bus``'s loop, or None."""
        if off is not None:
            self._path = ("python", off)
            return None
        if auth is not None and self.core == "python":
            self._path = ("python", "with a key the bus loop verifies and decodes each frame")
            return None
        if auth is not None:
            return self._keyed_path(auth, bus)
        self._path = (self.core, None)
        if self.core == "c":
            self.begin_encoded = self._core.begin_encoded
        if not bus:
            return self.fast_frame
        self._answers[bus] = self._answer_on(bus)
        return partial(self.fast_frame, bus=bus)

    def _keyed_path(self, auth: FrameAuth, bus: int) -> FastFrame:
        """``frame_path`` with a key, for bus ``bus``'s loop and its ``auth``."""
        classic = auth.layout is Layout.CLASSIC
        if self._frame_auths and self.begin_fd == classic:
            raise ValueError("the compiled core's frame path with a key: one layout on every bus")
        core = self._core
        core.use_keys(auth.key_for, classic=classic, bus=bus)
        self._frame_auths[bus] = auth
        if classic:
            self._auth_pairs[bus] = core.auth_pair_on(bus)
        else:
            self._auth_answers[bus] = core.auth_answer_on(bus)
        self.begin_fd = not classic
        if len(self._frame_auths) == self._buses:
            self.begin_encoded = core.begin_protected  # every bus's nodes have their keys
        self._path = ("c", None)
        if not bus:
            self._frame_auth = auth
            self._auth_pair = self._auth_pairs.get(0)
            self._auth_answer = self._auth_answers.get(0)
        fast = self.fast_auth_pair if classic else self.fast_auth_frame
        return fast if not bus else partial(fast, bus=bus)

    def fast_frame(self, frame: can.Message, now: int, bus: int = 0) -> Taken | None:
        """For a frame the bus loop has not decoded: an ACK, COMMITTED or ABORTED of a managed
        node goes through decode, rules, the decision on an ACK (commit, abort when stopping)
        and encode in one C call, its frames are held in the pass and what it did is returned
        (``ANSWERED``: the books, replies, the next grant are the service's). In the same call
        a TELEMETRY is taken by the tables in C (the TELEMETRY table, the witness, the held
        JOINs: the service gets only the words of what they found), a RETURN is held by the
        witness or ruled, a JOIN held. None, nothing done: any other frame, one that names a
        transaction never begun (judged on the usual path, an intrusion), listen-only, outside
        a loop pass. The bus loop then takes it as usual. ``bus``: the index of the bus it
        arrived on; its frames go to that bus's supervisor."""
        answer = self._answers[bus] if bus else self._answer
        passes = self._pass
        if self._listen_only or not passes.depth:
            return None
        status, actions, frames, decoded, verdict = answer(
            frame.arbitration_id,
            frame.data,
            frame.is_extended_id,
            frame.is_remote_frame,
            now,
            self._stopping.asked,
        )
        node = frame.arbitration_id & 0xFF | bus << BUS_SHIFT  # its session key
        if not status:  # an answer the rules took (nothing decoded, no verdict)
            self.frames += 1
            passes.held += [RawFrame(i, d, False, bus) for i, d in frames]  # first, in order
            return ANSWERED, node, actions, 0
        if verdict & self._join_bit:  # a JOIN held in C
            self.frames += 1
            return JOIN_HELD, node, None, 0
        if verdict & self._held_bit:  # a RETURN the witness in C held
            self.frames += 1
            return HELD, node, decoded, verdict & ~self._held_bit
        if verdict:  # a TELEMETRY the table and the witness in C took: what it shows, there
            self.frames += 1
            return TELEMETRY, node, decoded, verdict
        if decoded is not None:  # a RETURN, JOIN or DEBIT: as if the loop had decoded it
            self.frames += 1
            return DECODED, node, decoded, 0
        return None

    def fast_auth_frame(self, frame: can.Message, now: int, bus: int = 0) -> Taken | None:
        """``fast_frame`` with a key, FD layout: an ACK, COMMITTED or ABORTED of a managed node
        is verified (MAC, freshness), taken by the rules and answered with frames protected in
        one C call; what it shows of the node's freshness is noted (``FrameAuth.took``). None,
        nothing done: any other frame (TELEMETRY, JOIN, RETURN, DEBIT, the own direction), one
        refused (the loop's usual path counts and reports it), an answer ahead of the session.
        ``bus``: as ``fast_frame``'s (its keys and counters are that bus's)."""
        if self._listen_only or not self._pass.depth:
            return None
        answer = self._auth_answers[bus] if bus else self._auth_answer
        auth = self._frame_auths[bus] if bus else self._frame_auth
        assert answer is not None and auth is not None
        ident = frame.arbitration_id
        status, actions, frames, fv = answer(
            ident, frame.data, frame.is_extended_id, frame.is_remote_frame, now,
            self._stopping.asked,
        )  # fmt: skip
        if status:
            return None
        node = ident & 0xFF
        auth.took(MsgType(ident >> 8 & 0xF), node, fv)
        self.frames += 1
        self._pass.held += [RawFrame(i, d, True, bus) for i, d in frames]
        return ANSWERED, node | bus << BUS_SHIFT, actions, 0

    def fast_auth_pair(self, frame: can.Message, now: int, bus: int = 0) -> Taken | None:
        """``fast_auth_frame`` in the classic layout: the MAC frame of an ACK, COMMITTED or
        ABORTED of a managed node, with the message the loop's ``FrameAuth`` keeps for it,
        goes to C, where the pair is verified, taken by the rules and answered with frames
        protected (each followed by its MAC frame) in one call; the message then waits no
        more. None, nothing done (the message still waits): any other frame (a message
        waits for its MAC frame on the usual path), a MAC frame without such a message, one
        refused (the usual path pairs, counts and reports it as ever), an answer ahead of the
        session. ``bus``: as ``fast_frame``'s (its loop's ``FrameAuth`` keeps the message)."""
        ident = frame.arbitration_id
        if ident >> 8 & 0xF != _MAC_TO_SUPERVISOR or self._listen_only or not self._pass.depth:
            return None
        pair = self._auth_pairs[bus] if bus else self._auth_pair
        auth = self._frame_auths[bus] if bus else self._frame_auth
        assert pair is not None and auth is not None
        node = ident & 0xFF
        waiting = auth.pending.get(node)
        if waiting is None or waiting[0].TYPE not in _ANSWERS:
            return None
        msg, data = waiting
        status, actions, frames, fv = pair(
            auth.codec.arbitration_id(msg.TYPE, node), data, ident, frame.data,
            frame.is_extended_id, frame.is_remote_frame, now, self._stopping.asked,
        )  # fmt: skip
        if status:
            return None
        auth.took_waiting(node, fv)
        self.frames += 1
        self._pass.held += [RawFrame(i, d, False, bus) for i, d in frames]
        return ANSWERED, node | bus << BUS_SHIFT, actions, 0
