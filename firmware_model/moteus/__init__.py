"""An emulated moteus controller (CAN-FD register protocol) with the CiA 402 drive's motor physics.

- ``servo``: ``ServoModel`` (pure) and ``ServoFace`` (the model on a python-can bus);
- ``live_bench``: ``canergy supervisor --moteus`` against it on python-can's virtual bus.
"""
