"""C client vs Python client, host time per received frame, same frames, same run.

    make -C firmware bench      (builds build/bench_frames, then runs this with the venv)

Frames: INTENTION then COMMIT for 20,000 transactions of 100 mJ to node 5, as a supervisor
sends them. Per frame each client decodes strictly, runs the hardened rules and builds its reply
(and its NV record when the books change); neither run does I/O. Median of 9 runs each.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from canergy.codec import Codec
from canergy.core import Client
from canergy.core.state import ClientState
from canergy.messages import Commit, Direction, Intention
from firmware_model.nvstore import pack_record

NODE, TXS, REPEAT = 5, 20_000, 9


def frames(codec: Codec) -> list[tuple[int, bytes]]:
    out = []
    for tx in range(1, TXS + 1):
        out.append(codec.encode(Intention(NODE, tx & 0xFFFF, 100, (tx - 1) * 100 & 0xFFFFFF)))
        out.append(codec.encode(Commit(NODE, tx & 0xFFFF, 100)))
    return out


def python_ns(codec: Codec, raw: list[tuple[int, bytes]]) -> tuple[float, int]:
    runs = []
    usable = 0
    for _ in range(REPEAT):
        client = Client(NODE, state=ClientState(NODE))
        t0 = time.perf_counter_ns()
        for i, (ident, data) in enumerate(raw):
            msg = codec.decode(ident, data, direction=Direction.TO_CLIENT)
            for action in client.receive(msg, 1000 + i):  # type: ignore[arg-type]
                if type(action).__name__ == "Persist":
                    pack_record(client.state)  # what the node writes before it sends
                elif type(action).__name__ == "Send":
                    codec.encode(action.message)  # type: ignore[attr-defined]
        runs.append((time.perf_counter_ns() - t0) / len(raw))
        usable = client.state.usable
    return statistics.median(runs), usable


def main() -> int:
    binary = Path(sys.argv[1])
    codec = Codec()
    raw = frames(codec)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "frames.txt"
        path.write_text("".join(f"{i:08X} {d.hex()}\n" for i, d in raw))
        c_out = subprocess.run([str(binary), str(path)], capture_output=True, text=True, check=True)
    c_ns, c_usable = float(c_out.stdout.split()[0]), int(c_out.stdout.split()[2])
    py_ns, py_usable = python_ns(codec, raw)
    assert c_usable == py_usable == TXS * 100_000, (c_usable, py_usable)  # both committed all
    print(f"frames per run: {len(raw)} (median of {REPEAT} runs each)")
    print(f"C client:      {c_ns:8.1f} ns/frame")
    print(f"Python client: {py_ns:8.1f} ns/frame")
    print(f"C speed-up:    {py_ns / c_ns:8.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
