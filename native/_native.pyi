"""Type stub for clothball._native, the compiled core (see native/bindings.cpp).

Use it through clothball.game.Cloth, which validates arguments; this module trusts them.
"""

from types import ModuleType

import numpy as np
import numpy.typing as npt

EFFECT_BITS: dict[str, int]
INTEGRATOR_IDS: dict[str, int]  # Config.integrator of each scene integrator name
falcon: ModuleType  # the Novint Falcon driver (native/falcon/bind_falcon.cpp)

class Config:
    n: int
    rest_len: float
    node_mass: float
    k_struct: float
    k_shear: float
    k_bend: float
    struct_compress: float
    gravity: list[float]
    damping: float
    ball_radius: float
    ball_mass: float
    ball_k: float
    ball_damping: float
    coupling_k: float
    air_density: float
    drag: float
    lift: float
    max_strain: float
    strain_iterations: int
    threads: int
    integrator: int
    cg_max_iterations: int
    cg_tolerance: float
    effects: int
    def __init__(self) -> None: ...

_F64 = npt.NDArray[np.float64]

class Engine:
    def __init__(self, backend: str, double_precision: bool, config: Config) -> None: ...
    def configure(self, config: Config) -> None: ...
    def set_hips(self, hips: npt.ArrayLike) -> None: ...
    def set_wind(self, wind: npt.ArrayLike) -> None: ...
    def set_state(self, positions: npt.ArrayLike, velocities: npt.ArrayLike) -> None: ...
    def set_ball(self, position_velocity: npt.ArrayLike) -> None: ...
    def positions(self) -> _F64: ...
    def velocities(self) -> _F64: ...
    def normals(self) -> _F64: ...
    def ball(self) -> _F64: ...
    def corners(self) -> _F64: ...
    def step(self, frames: int, substeps: int, dt: float) -> None: ...
    def state_finite(self) -> bool: ...
    def compiled_effects(self) -> int: ...

def cuda_unavailable_reason() -> str: ...
def cpu_threads() -> int: ...
def cuda_copy_bandwidth_gbs(bytes: int, reps: int = 20) -> float: ...
