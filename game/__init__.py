"""clothball.game: scenes, the cloth simulation facade, game logic and the clients."""

from .cloth import Cloth, SimulationError, cuda_unavailable_reason
from .oracle import ReferenceCloth
from .scene import Scene, SceneError

__all__ = [
    "Cloth",
    "ReferenceCloth",
    "Scene",
    "SceneError",
    "SimulationError",
    "cuda_unavailable_reason",
]
