"""canergy: passive energy budget transactions between a supervisor and CAN client nodes."""

from canergy.codec import Codec, DecodeError, DecodeErrorReason
from canergy.core import Client, LocalProtocolError, Supervisor, Timing
from canergy.ledger import Ledger, ledger
from canergy.units import format_energy, parse_energy

__version__ = "0.1.0"

__all__ = [
    "Client",
    "Codec",
    "DecodeError",
    "DecodeErrorReason",
    "Ledger",
    "LocalProtocolError",
    "Supervisor",
    "Timing",
    "__version__",
    "format_energy",
    "ledger",
    "parse_energy",
]
