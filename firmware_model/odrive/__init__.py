"""An emulated ODrive axis (CAN Simple) with the CiA 402 drive's motor physics.

- ``axis``: ``AxisModel`` (pure) and ``AxisFace`` (the model on a python-can bus);
- ``live_bench``: ``canergy supervisor --odrive`` against it on python-can's virtual bus.
"""
