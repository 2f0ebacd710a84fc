"""An emulated CiA 402 servo drive (EPOS4/Elmo-like) that knows the energy it draws.

- ``motor``: DC motor physics and exact energy accounts (pure);
- ``power``: the CiA 402 power state machine and operation modes (pure);
- ``model``: ``DriveModel``, state machine + motor + object dictionary, time passed in;
- ``canopen_face``: ``DriveFace``, the model as a python-canopen ``LocalNode`` on a bus;
- ``python -m firmware_model.drive``: one drive in real time on any python-can bus.
"""

from firmware_model.drive.model import EDS, DriveAbort, DriveModel
from firmware_model.drive.motor import LoadTorque, MotorParams

__all__ = ["EDS", "DriveAbort", "DriveModel", "LoadTorque", "MotorParams"]
