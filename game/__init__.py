"""clothball.game: scenes, the cloth simulation facade, game logic and the clients."""

from .sim.batch import ClothBatch
from .sim.cloth import Cloth, SimulationError, cuda_unavailable_reason
from .sim.oracle import ReferenceCloth
from .sim.scene import Scene, SceneError

__all__ = [
    "Cloth",
    "ClothBatch",
    "ReferenceCloth",
    "Scene",
    "SceneError",
    "SimulationError",
    "cuda_unavailable_reason",
]
