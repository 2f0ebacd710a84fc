"""CANopen beside canergy on one bus: NMT, heartbeats, SDO audit, the CiA 402 drives' links."""
