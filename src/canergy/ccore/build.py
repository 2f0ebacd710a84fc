"""The cffi builder of ``canergy.ccore._supervisor``: firmware/'s supervisor role, compiled for
this host with room for every node id (127 sessions).

setup.py builds it where a C compiler exists (``pip install``); without one canergy installs
without it and ``canergy supervisor`` runs the Python core. ``python -m canergy.ccore.build``
builds it in place (a checkout whose install skipped it).
"""

from __future__ import annotations

from pathlib import Path

from cffi import FFI

ROOT = Path(__file__).resolve().parents[3]
SOURCES = ("codec.c", "nv.c", "session.c", "supervisor.c")
"""What the supervisor role links: the codec, CRC-32 (nv.c), the session rules, Us and NV."""
NODES = 127

CDEF = """
#define CANERGY_OK ...
#define CANERGY_ERR_ARGUMENT ...
#define CANERGY_ERR_PHASE ...
#define CANERGY_ERR_AMOUNT ...
#define CANERGY_RX_OTHER_NODE ...
#define CANERGY_RX_AHEAD ...
#define CANERGY_RX_CALLER ...
#define CANERGY_DECODE_OK ...
#define CANERGY_SUPERVISOR_NODES ...
#define CANERGY_SUP_ACKNOWLEDGED ...
#define CANERGY_SUP_RETURN_CREDITED ...
#define CANERGY_SUP_ADMITTED ...
#define CANERGY_NEVER ...
#define CANERGY_ERR_WINDOW ...
#define CANERGY_ERR_UNCONFIRMED ...

struct canergy_msg {
    uint32_t delivered_mj; uint32_t level_mj; uint16_t tx; uint16_t seq; uint16_t nonce;
    uint16_t amount_mj; uint8_t type; uint8_t node; uint8_t flags; uint8_t witness; ...;
};
struct canergy_frame { uint32_t id; uint8_t dlc; uint8_t data[8]; ...; };
struct canergy_rx_frame { uint32_t id; const uint8_t *data; size_t len; bool extended;
    bool remote; ...; };
struct canergy_session_timing { uint32_t response_timeout_us; uint8_t retries; uint8_t rules;
    uint16_t window; ...; };
struct canergy_session {
    uint64_t delivered_uj; uint64_t returned_uj; uint64_t deadline; uint32_t tx;
    uint32_t returns_credited; uint32_t reserved_uj; uint32_t resume_from; uint32_t resume_to;
    uint32_t resume_nonce; int32_t witness; uint16_t sync_nonce; uint8_t node; uint8_t phase;
    uint8_t decision; uint8_t tries; ...;
};
struct canergy_supervisor_config { uint32_t id_base; struct canergy_session_timing timing; ...; };
struct canergy_supervisor {
    int64_t usable_uj; uint64_t injected_uj; uint64_t withdrawn_uj;
    struct canergy_session sessions[...];
    uint32_t id_base; uint8_t count; ...;
};
struct canergy_supervisor_event {
    uint32_t tx; uint32_t amount_uj; uint8_t node; uint8_t resolved; uint8_t flags; ...;
};
struct canergy_supervisor_out {
    struct canergy_frame frames[...]; struct canergy_supervisor_event events[...];
    uint8_t frame_count; uint8_t event_count; uint8_t persist; ...;
};

int canergy_supervisor_init(struct canergy_supervisor *sup,
    const struct canergy_supervisor_config *cfg, const uint8_t *nodes, uint8_t count,
    uint64_t initial_uj);
int canergy_supervisor_begin(struct canergy_supervisor *sup, uint8_t node, uint32_t amount_uj,
    uint64_t now, struct canergy_supervisor_out *out);
int canergy_supervisor_decide(struct canergy_supervisor *sup, uint8_t node, bool commit,
    uint64_t now, struct canergy_supervisor_out *out);
int canergy_supervisor_on_frame(struct canergy_supervisor *sup,
    const struct canergy_rx_frame *frame, uint64_t now, struct canergy_supervisor_out *out);
int canergy_supervisor_on_msg(struct canergy_supervisor *sup, const struct canergy_msg *m,
    uint64_t now, struct canergy_supervisor_out *out);
int canergy_supervisor_on_answer(struct canergy_supervisor *sup,
    const struct canergy_rx_frame *frame, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_msg *m);
void canergy_supervisor_on_timer(struct canergy_supervisor *sup, uint64_t now,
    struct canergy_supervisor_out *out);
uint64_t canergy_supervisor_deadline(const struct canergy_supervisor *sup);
int canergy_host_answer(struct canergy_supervisor *sup, uint32_t id, unsigned kind,
    const uint8_t *data, size_t len, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_msg *m);
void canergy_supervisor_restart(struct canergy_supervisor *sup, uint64_t now);
void canergy_supervisor_start(struct canergy_supervisor *sup, uint16_t nonce, uint64_t now,
    struct canergy_supervisor_out *out);
int canergy_supervisor_start_without(struct canergy_supervisor *sup, uint8_t node);
uint8_t canergy_supervisor_unconfirmed(const struct canergy_supervisor *sup, uint8_t *nodes);
int canergy_supervisor_inject(struct canergy_supervisor *sup, uint64_t amount_uj);
"""

HOST_SOURCE = """
#include "canergy/supervisor.h"

/* The fast path's call with the frame as arguments: one call, no struct filled field by field
   from Python (kind: bit 0 extended identifier, bit 1 remote frame). */
static int canergy_host_answer(struct canergy_supervisor *sup, uint32_t id, unsigned kind,
    const uint8_t *data, size_t len, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_msg *m)
{
    struct canergy_rx_frame rx = {0};
    rx.id = id;
    rx.data = data;
    rx.len = len;
    rx.extended = (kind & 1U) != 0U;
    rx.remote = (kind & 2U) != 0U;
    return canergy_supervisor_on_answer(sup, &rx, now, abort_acks, out, m);
}
"""
"""Compiled with the role: what only the host's binding calls."""


def builder(root: Path = ROOT) -> FFI:
    """The builder, naming firmware/ under ``root`` (setup.py needs paths relative to it)."""
    firmware = root / "firmware"
    ffi = FFI()
    ffi.cdef(CDEF)
    ffi.set_source(
        "canergy.ccore._supervisor",
        HOST_SOURCE,
        sources=[str(firmware / "src" / name) for name in SOURCES],
        include_dirs=[str(firmware / "include")],
        define_macros=[("CANERGY_SUPERVISOR_NODES", f"{NODES}U")],
        extra_compile_args=["-std=c99", "-O2"],
    )
    return ffi


def build_in_place() -> Path:
    """Compile into this checkout's source tree (objects in a temporary directory); returns the
    extension's path."""
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        built = Path(builder().compile(tmpdir=tmp, verbose=False))
        target = Path(__file__).parent / built.name
        shutil.copyfile(built, target)
    return target


if __name__ == "__main__":
    print(build_in_place())
