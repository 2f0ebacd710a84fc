"""Each command's one line for ``canergy --help``, kept apart from the commands so that the
list is built without importing any of them (a command is imported only when it runs)."""

SUMMARIES: dict[str, str] = {
    "demo": "supervisor and clients on python-can's virtual bus under injected faults",
    "check": "exhaustively model-check the protocol core within bounds",
    "prove": "prove that the rules never create energy, for any number of transactions",
    "dbc": "write the DBC describing canergy's frames",
    "rules": "print the transition tables; --docs DIR also writes the reference and diagrams",
    "supervisor": "grant energy to client nodes on a CAN bus",
    "grant": "one grant: through a running supervisor (--control) or as a single run",
    "gateway": "a client of the supervisor above and the supervisor of the bus below",
    "ledger": "the conservation ledger of a bus or a tree of buses, from status files",
    "simulate": "discrete-event simulation of the paper's case study (and more)",
    "sweep": "Monte Carlo over loss rates, many seeds per point, all cores",
    "dump": "candump-style live view with every canergy frame decoded",
    "decode": "decode a capture: candump text from stdin or any python-can log file",
    "audit": "rebuild transactions from a capture and check the protocol and passivity",
    "monitor": "full-screen live view of every node's budget and transactions",
    "plot": "plot a capture: per node granted, returned and holdable energy, and the messages",
    "keys": "create key files for authenticated mode (--auth)",
    "bench": "benchmarks: codec, core, live stack vs CANopen SDO, wire, memory; with bus flags "
    "the live stack on that bus against node processes",
    "bridge": "a fault-injecting bridge between two CAN buses, for tests and benches",
    "inline": "MIT-mode motors in line between two buses: commands clamped under a budget",
}
"""Command -> its summary, in the order ``canergy --help`` lists them."""
