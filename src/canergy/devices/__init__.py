"""Guarded devices beyond canergy nodes: the device-profile interface and its profiles.

``profile`` is the interface a device type implements (its limits, their envelope, how they are
compared when read back, what its stop can draw); ``guard`` is the sans-IO guard that works for
any profile; ``odrive`` is the ODrive CAN Simple profile, ``moteus`` the moteus CAN-FD register
protocol's; ``mit`` the MIT-mode frames, models and clamp, and ``mit_gate`` an MIT-mode motor
guarded in line (the application's commands pass through it: ``canergy.live.devices.mit_bus``).
``proxy`` is the proxy client's books every guard keeps, the CiA 402 guard (``canergy.cia402``)
included. CiA 402 is a profile too (``canergy.cia402.profile``: its envelope, the writes its
bound depends on and their read-back), with a guard of its own for what only it has (the counter
mode, object writes charged at the drive's reach until read back, tapering; docs/guide/drives.md).
"""
