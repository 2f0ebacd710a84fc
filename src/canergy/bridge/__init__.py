"""A fault-injecting bridge between two CAN buses, for integration tests of nodes and for benches.

``canergy.bridge.schedule`` decides, sans-IO, what happens to each frame (seeded, replayable,
counted); ``canergy.bridge.link`` carries frames between two python-can buses through it;
``canergy bridge`` is the command line.
"""
