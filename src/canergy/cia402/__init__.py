"""Off-the-shelf CiA 402 drives under an energy budget: metering and the guard (sans-IO)."""
