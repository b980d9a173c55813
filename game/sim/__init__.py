"""The physics: scenes, the ``Cloth`` facade over the native engine, the stability bound and
the NumPy float64 oracle. Imports nothing of the package but the native module."""

import os as _os

# The CPU engine's OpenMP threads sleep between parallel regions instead of spinning, taking
# the cores from everything else between frames (game.sim.threads). Read by the OpenMP
# runtime when the native module loads it, so set before anything imports that module.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
