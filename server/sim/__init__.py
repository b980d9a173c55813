"""The rooms' simulation: simulated time locked to wall time in 1 ms frames, every room of
one scene stepped by one native frame loop (docs/frameloop.md).

``roomsim`` (a room's handle: ``RoomSim``), ``pool`` (the server's workers: ``SimPool``),
``worker`` (a frame loop and its Python side: ``FrameWorker``), ``results`` (what a frame
hands the event loop: ``FrameResult``; the lateness ring: ``Samples``).
"""

from .pool import WORKER_CAPACITY, SimPool
from .results import FrameResult, Samples
from .roomsim import RoomSim

__all__ = ["WORKER_CAPACITY", "FrameResult", "RoomSim", "Samples", "SimPool"]
