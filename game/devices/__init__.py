"""Input devices that move a corner's hand position: mouse, bot, Falcon.

Every device implements the small interface in ``base.Device``.
"""

from .base import CornerState, Device, Reach

__all__ = ["CornerState", "Device", "Reach"]
