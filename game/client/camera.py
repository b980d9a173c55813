"""An orbit camera: matrices, picking rays and projection to the screen (pure NumPy).

World: y up, the cloth around ``target``. The eye sits at ``distance`` from the target, at
``yaw`` around y (0: on the +z side looking towards -z) and ``pitch`` above the horizon.
Matrices are column-vector convention (``clip = P @ V @ world``), handed to GL transposed
(row-major NumPy -> column-major GL).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


def perspective(fovy_deg: float, aspect: float, near: float, far: float) -> np.ndarray:
    f = 1.0 / math.tan(math.radians(fovy_deg) / 2.0)
    m = np.zeros((4, 4))
    m[0, 0] = f / aspect
    m[1, 1] = f
    m[2, 2] = (far + near) / (near - far)
    m[2, 3] = 2.0 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    up = np.array([0.0, 1.0, 0.0]) if up is None else np.asarray(up, float)
    f = target - eye
    f /= np.linalg.norm(f)
    s = np.cross(f, up)
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


@dataclass
class OrbitCamera:
    target: np.ndarray = field(default_factory=lambda: np.zeros(3))
    distance: float = 2.2
    yaw: float = 0.0  # radians around +y; 0: eye on the +z side
    pitch: float = 0.75  # radians above the horizon
    fovy: float = 45.0
    near: float = 0.02
    far: float = 50.0

    @property
    def eye(self) -> np.ndarray:
        cp = math.cos(self.pitch)
        return self.target + self.distance * np.array(
            [cp * math.sin(self.yaw), math.sin(self.pitch), cp * math.cos(self.yaw)])

    def face(self, point: np.ndarray) -> None:
        """Turn so that ``point`` (seen from above) is on the viewer's side of the target."""
        d = np.asarray(point, float) - self.target
        if abs(d[0]) + abs(d[2]) > 1e-9:
            self.yaw = math.atan2(d[0], d[2])

    def orbit(self, dyaw: float, dpitch: float) -> None:
        self.yaw += dyaw
        self.pitch = float(np.clip(self.pitch + dpitch, 0.05, 1.5))

    def zoom(self, factor: float) -> None:
        self.distance = float(np.clip(self.distance * factor, 0.3, 20.0))

    def view(self) -> np.ndarray:
        return look_at(self.eye, self.target)

    def projection(self, width: int, height: int) -> np.ndarray:
        return perspective(self.fovy, max(1, width) / max(1, height), self.near, self.far)

    def view_projection(self, width: int, height: int) -> np.ndarray:
        return self.projection(width, height) @ self.view()

    def ray(self, x: float, y: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """The ray (origin, unit direction) through window pixel (x, y), origin bottom-left
        as pyglet reports mouse positions."""
        inv = np.linalg.inv(self.view_projection(width, height))
        nx, ny = 2.0 * x / max(1, width) - 1.0, 2.0 * y / max(1, height) - 1.0
        p0 = inv @ np.array([nx, ny, -1.0, 1.0])
        p1 = inv @ np.array([nx, ny, 1.0, 1.0])
        a, b = p0[:3] / p0[3], p1[:3] / p1[3]
        d = b - a
        return a, d / np.linalg.norm(d)

    def project(self, p: np.ndarray, width: int, height: int) -> tuple[float, float, bool]:
        """Window pixel (x, y) of world point ``p`` and whether it is in front of the eye."""
        c = self.view_projection(width, height) @ np.append(np.asarray(p, float), 1.0)
        if c[3] <= 1e-9:
            return 0.0, 0.0, False
        ndc = c[:3] / c[3]
        return (ndc[0] + 1.0) * 0.5 * width, (ndc[1] + 1.0) * 0.5 * height, True
