"""An emulated MIT-mode motor (CubeMars AK, Damiao DM) with the CiA 402 drive's motor physics.

- ``motor``: ``MitMotorModel`` (pure) and ``MitFace`` (the model on a python-can bus).
"""
