"""Embedded client emulator, written the way the firmware would be ported to C.

``nvstore`` holds the fixed-layout non-volatile record (29 bytes) in two CRC-checked slots;
``actuator`` draws power from the usable budget and halts at zero; ``node`` wraps the shared
core's ``Client`` (the protocol rules are never copied here) with the NV writes, telemetry and a
return policy; ``canopen_node`` makes nodes CANopen slaves; ``python -m firmware_model`` runs
one or many nodes on any python-can bus.
"""
