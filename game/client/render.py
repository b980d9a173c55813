"""Drawing a ``RenderFrame`` with OpenGL 3.3 core shaders (pyglet 2).

* The cloth: triangles lit from their vertex normals (computed on the client for the
  frames it renders) under one directional light plus a rim of ambient, two-sided (the
  underside is darker), as in the paper's Fig. 1a; ``wire`` draws the spring grid on top
  (Fig. 1b) or alone.
* The ball: a lit sphere.
* Corner handles: a sphere per corner in its seat's colour, a smaller one at each hand,
  and the line between them; the player's own line is a wider band coloured by force.
* Guarded edges: a band along each edge of the cloth in the colour of the seat guarding
  it (grey: nobody).

Bands are built on the CPU each frame (a few hundred vertices); the cloth's buffers are
updated in place (``glBufferSubData``). Importing this module needs a GL context (pyglet
opens one on import), so the window imports it lazily.
"""

from __future__ import annotations

import ctypes
import math

import numpy as np
from pyglet import gl
from pyglet.graphics.shader import Shader, ShaderProgram

from .camera import OrbitCamera
from .interp import (
    BALL_COLOUR,
    CLOTH_BACK,
    CLOTH_FRONT,
    FLOOR_COLOUR,
    WIRE_COLOUR,
    RenderFrame,
    grid_edge,
    grid_lines,
    grid_triangles,
)

LIT_VS = """#version 330 core
in vec3 position;
in vec3 normal;
uniform mat4 u_vp;
uniform mat4 u_model;
out vec3 v_pos;
out vec3 v_normal;
void main() {
    vec4 world = u_model * vec4(position, 1.0);
    v_pos = world.xyz;
    v_normal = mat3(u_model) * normal;
    gl_Position = u_vp * world;
}
"""

LIT_FS = """#version 330 core
in vec3 v_pos;
in vec3 v_normal;
uniform vec3 u_front;
uniform vec3 u_back;
uniform vec3 u_light;   // direction towards the light, unit
uniform vec3 u_eye;
out vec4 frag;
void main() {
    vec3 n = normalize(v_normal);
    vec3 base = u_front;
    if (!gl_FrontFacing) { n = -n; base = u_back; }
    vec3 v = normalize(u_eye - v_pos);
    if (dot(n, v) < 0.0) n = -n;
    float diff = max(dot(n, u_light), 0.0);
    vec3 h = normalize(u_light + v);
    float spec = pow(max(dot(n, h), 0.0), 32.0) * 0.15;
    vec3 c = base * (0.30 + 0.70 * diff) + vec3(spec);
    frag = vec4(c, 1.0);
}
"""

FLAT_VS = """#version 330 core
in vec3 position;
in vec4 colour;
uniform mat4 u_vp;
uniform float u_lift;
out vec4 v_colour;
void main() {
    v_colour = colour;
    vec4 p = u_vp * vec4(position, 1.0);
    p.z -= u_lift * p.w;   // drawn over the cloth it lies on
    gl_Position = p;
}
"""

FLAT_FS = """#version 330 core
in vec4 v_colour;
out vec4 frag;
void main() { frag = v_colour; }
"""


def gl_matrix(m: np.ndarray) -> tuple[float, ...]:
    """A row-major NumPy 4x4 as the column-major sequence GL expects."""
    return tuple(float(x) for x in np.asarray(m, dtype=np.float64).T.ravel())


def uv_sphere(rings: int = 12, segments: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere: positions (= normals) (k, 3) float32 and triangle indices uint32."""
    th = np.linspace(0.0, math.pi, rings + 1)
    ph = np.linspace(0.0, 2.0 * math.pi, segments + 1)
    t, p = np.meshgrid(th, ph, indexing="ij")
    pts = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], axis=-1)
    idx = []
    w = segments + 1
    for i in range(rings):
        for j in range(segments):
            a, b = i * w + j, i * w + j + 1
            c, d = a + w, b + w
            idx += [a, c, b, b, c, d]
    return pts.reshape(-1, 3).astype(np.float32), np.asarray(idx, dtype=np.uint32)


def band(points: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """A triangle strip (2k, 3) along ``points`` (k, 3), widened by ``offsets`` (k, 3)."""
    p = np.asarray(points, dtype=np.float32)
    o = np.asarray(offsets, dtype=np.float32)
    out = np.empty((2 * len(p), 3), dtype=np.float32)
    out[0::2] = p - o
    out[1::2] = p + o
    return out


def strip_to_triangles(strip: np.ndarray) -> np.ndarray:
    """Triangle-strip vertices -> plain triangles (so several strips share one draw)."""
    k = len(strip)
    if k < 3:
        return np.zeros((0, 3), dtype=np.float32)
    i = np.arange(k - 2)
    a, b, c = i, i + 1, i + 2
    # keep the winding consistent (irrelevant here: no culling)
    return strip[np.stack([a, b, c], axis=1).ravel()]


class Buffers:
    """One VAO with a float32 VBO per attribute and an optional index buffer."""

    def __init__(self, program: ShaderProgram, attrs: dict[str, int],
                 indices: np.ndarray | None = None, capacity: int = 0) -> None:
        self.vao = gl.GLuint()
        gl.glGenVertexArrays(1, ctypes.byref(self.vao))
        gl.glBindVertexArray(self.vao)
        self.vbos: dict[str, gl.GLuint] = {}
        self.sizes: dict[str, int] = {}
        self.capacity: dict[str, int] = {}
        for name, size in attrs.items():
            vbo = gl.GLuint()
            gl.glGenBuffers(1, ctypes.byref(vbo))
            gl.glBindBuffer(gl.GL_ARRAY_BUFFER, vbo)
            gl.glBufferData(gl.GL_ARRAY_BUFFER, max(1, capacity) * size * 4, None,
                            gl.GL_DYNAMIC_DRAW)
            loc = program.attributes[name]["location"]
            gl.glEnableVertexAttribArray(loc)
            gl.glVertexAttribPointer(loc, size, gl.GL_FLOAT, gl.GL_FALSE, 0, 0)
            self.vbos[name], self.sizes[name] = vbo, size
            self.capacity[name] = max(1, capacity)
        self.ebo: gl.GLuint | None = None
        self.count = 0
        if indices is not None:
            self.set_indices(indices)
        gl.glBindVertexArray(0)

    def set_indices(self, indices: np.ndarray) -> None:
        idx = np.ascontiguousarray(indices, dtype=np.uint32)
        gl.glBindVertexArray(self.vao)
        if self.ebo is None:
            self.ebo = gl.GLuint()
            gl.glGenBuffers(1, ctypes.byref(self.ebo))
        gl.glBindBuffer(gl.GL_ELEMENT_ARRAY_BUFFER, self.ebo)
        gl.glBufferData(gl.GL_ELEMENT_ARRAY_BUFFER, idx.nbytes, idx.ctypes.data,
                        gl.GL_STATIC_DRAW)
        self.count = len(idx)
        gl.glBindVertexArray(0)

    def upload(self, name: str, data: np.ndarray) -> None:
        arr = np.ascontiguousarray(data, dtype=np.float32)
        n = arr.size // self.sizes[name]
        gl.glBindBuffer(gl.GL_ARRAY_BUFFER, self.vbos[name])
        if n > self.capacity[name]:
            gl.glBufferData(gl.GL_ARRAY_BUFFER, arr.nbytes, arr.ctypes.data, gl.GL_DYNAMIC_DRAW)
            self.capacity[name] = n
        else:
            gl.glBufferSubData(gl.GL_ARRAY_BUFFER, 0, arr.nbytes, arr.ctypes.data)
        if self.ebo is None:
            self.count = n

    def draw(self, mode: int, count: int | None = None) -> None:
        gl.glBindVertexArray(self.vao)
        n = self.count if count is None else count
        if n > 0:
            if self.ebo is not None:
                gl.glDrawElements(mode, n, gl.GL_UNSIGNED_INT, 0)
            else:
                gl.glDrawArrays(mode, 0, n)
        gl.glBindVertexArray(0)

    def delete(self) -> None:
        for vbo in self.vbos.values():
            gl.glDeleteBuffers(1, ctypes.byref(vbo))
        if self.ebo is not None:
            gl.glDeleteBuffers(1, ctypes.byref(self.ebo))
        gl.glDeleteVertexArrays(1, ctypes.byref(self.vao))


class Renderer:
    """Draws ``RenderFrame``s. Create it with the window's context current."""

    def __init__(self) -> None:
        self.lit = ShaderProgram(Shader(LIT_VS, "vertex"), Shader(LIT_FS, "fragment"))
        self.flat = ShaderProgram(Shader(FLAT_VS, "vertex"), Shader(FLAT_FS, "fragment"))
        self.wire = False  # wire mesh over the shaded cloth
        self.wire_only = False
        self.light = np.array([0.35, 1.0, 0.55]) / np.linalg.norm([0.35, 1.0, 0.55])
        self._n = 0
        self.cloth = Buffers(self.lit, {"position": 3, "normal": 3})
        self.wire_buf = Buffers(self.flat, {"position": 3, "colour": 4})
        sphere, sidx = uv_sphere()
        self.sphere = Buffers(self.lit, {"position": 3, "normal": 3}, sidx, len(sphere))
        self.sphere.upload("position", sphere)
        self.sphere.upload("normal", sphere)
        self.bands = Buffers(self.flat, {"position": 3, "colour": 4})
        self.floor = Buffers(self.flat, {"position": 3, "colour": 4})
        self.floor_y: float | None = None

    def _resize(self, n: int) -> None:
        self._n = n
        self.cloth.set_indices(grid_triangles(n))
        self.wire_buf.set_indices(grid_lines(n))
        self.wire_buf.upload("colour", np.tile(np.array([*WIRE_COLOUR, 1.0], np.float32),
                                               (n * n, 1)))

    def _floor(self, frame: RenderFrame) -> None:
        p = frame.positions
        lo, hi = p.reshape(-1, 3).min(axis=0), p.reshape(-1, 3).max(axis=0)
        size = float(max(hi[0] - lo[0], hi[2] - lo[2], 0.5))
        centre = (lo + hi) / 2
        y = float(np.mean(p[..., 1])) - 0.8 * size
        if self.floor_y is not None and abs(self.floor_y - y) < 0.5 * size:
            return
        self.floor_y = y
        lines = []
        ext = 2.0 * size
        for k in np.linspace(-ext, ext, 17):
            lines += [[centre[0] + k, y, centre[2] - ext], [centre[0] + k, y, centre[2] + ext]]
            lines += [[centre[0] - ext, y, centre[2] + k], [centre[0] + ext, y, centre[2] + k]]
        pts = np.asarray(lines, dtype=np.float32)
        self.floor.upload("position", pts)
        self.floor.upload("colour", np.tile(np.array([*FLOOR_COLOUR, 1.0], np.float32),
                                            (len(pts), 1)))

    def draw(self, frame: RenderFrame, camera: OrbitCamera, width: int, height: int) -> None:
        n = frame.positions.shape[0]
        if n != self._n:
            self._resize(n)
        vp = gl_matrix(camera.view_projection(width, height))
        eye = tuple(float(x) for x in camera.eye)
        gl.glEnable(gl.GL_DEPTH_TEST)
        gl.glDisable(gl.GL_CULL_FACE)
        gl.glEnable(gl.GL_BLEND)
        gl.glBlendFunc(gl.GL_SRC_ALPHA, gl.GL_ONE_MINUS_SRC_ALPHA)
        self._floor(frame)

        # lit things: cloth and spheres
        self.lit.use()
        self.lit["u_vp"] = vp
        self.lit["u_eye"] = eye
        self.lit["u_light"] = tuple(float(x) for x in self.light)
        self.lit["u_model"] = gl_matrix(np.eye(4))
        pos = frame.positions.reshape(-1, 3)
        if not self.wire_only:
            self.lit["u_front"] = CLOTH_FRONT
            self.lit["u_back"] = CLOTH_BACK
            self.cloth.upload("position", pos)
            self.cloth.upload("normal", frame.normals.reshape(-1, 3))
            self.cloth.draw(gl.GL_TRIANGLES)
        r = max(frame.ball_radius, 1e-3)
        self._sphere(frame.ball_position, r, BALL_COLOUR)
        size = float(np.ptp(pos[:, 0])) or 1.0
        for h in frame.handles:
            dim = 1.0 if h.kind != "empty" or h.own else 0.45
            col = tuple(c * dim for c in h.colour)
            self._sphere(h.position, 0.025 * size, col)
            if h.hip is not None:
                self._sphere(h.hip, 0.014 * size, col)
        self.lit.stop()

        # flat things: floor, wire, bands
        self.flat.use()
        self.flat["u_vp"] = vp
        self.flat["u_lift"] = 0.0
        self.floor.draw(gl.GL_LINES)
        if self.wire or self.wire_only:
            self.flat["u_lift"] = 0.0004
            self.wire_buf.upload("position", pos)
            self.wire_buf.draw(gl.GL_LINES)
        self.flat["u_lift"] = 0.0008
        tris, cols = self._bands(frame, camera, size)
        if len(tris):
            self.bands.upload("position", tris)
            self.bands.upload("colour", cols)
            self.bands.draw(gl.GL_TRIANGLES)
        self.flat.stop()
        gl.glDisable(gl.GL_DEPTH_TEST)

    def _sphere(self, centre: np.ndarray, radius: float, colour: tuple[float, ...]) -> None:
        m = np.eye(4)
        m[:3, :3] *= radius
        m[:3, 3] = centre
        self.lit["u_model"] = gl_matrix(m)
        self.lit["u_front"] = tuple(colour[:3])
        self.lit["u_back"] = tuple(colour[:3])
        self.sphere.draw(gl.GL_TRIANGLES)
        self.lit["u_model"] = gl_matrix(np.eye(4))

    def _bands(self, frame: RenderFrame, camera: OrbitCamera, size: float
               ) -> tuple[np.ndarray, np.ndarray]:
        p = frame.positions
        centre = p.reshape(-1, 3).mean(axis=0)
        tris, cols = [], []
        w = 0.012 * size
        for e in range(4):
            pts = grid_edge(p, e).astype(np.float64)
            out = pts - centre
            out[:, 1] = 0.0
            # outward across the edge: the component normal to the edge direction
            d = np.gradient(pts, axis=0)
            d[:, 1] = 0.0
            d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
            nrm = np.stack([-d[:, 2], np.zeros(len(d)), d[:, 0]], axis=1)
            sign = np.sign(np.sum(nrm * out, axis=1, keepdims=True))
            nrm *= np.where(sign == 0, 1.0, sign)
            t = strip_to_triangles(band(pts + nrm * w, nrm * w))
            tris.append(t)
            cols.append(np.tile(np.array([*frame.edge_colours[e], 1.0], np.float32),
                                (len(t), 1)))
        eye = camera.eye
        for h in frame.handles:
            if h.hip is None or h.own:
                continue
            t = self._line(h.position, h.hip, 0.004 * size, eye)
            tris.append(t)
            cols.append(np.tile(np.array([*h.colour, 0.8], np.float32), (len(t), 1)))
        if frame.pull is not None:
            width = 0.004 * size + min(0.012 * size, frame.pull.force * 0.0008 * size)
            t = self._line(frame.pull.corner, frame.pull.hand, width, eye)
            tris.append(t)
            cols.append(np.tile(np.array([*frame.pull.colour, 1.0], np.float32), (len(t), 1)))
        if not tris:
            return np.zeros((0, 3), np.float32), np.zeros((0, 4), np.float32)
        return np.concatenate(tris), np.concatenate(cols)

    @staticmethod
    def _line(a: np.ndarray, b: np.ndarray, width: float, eye: np.ndarray) -> np.ndarray:
        """A band from ``a`` to ``b`` facing the eye."""
        a, b = np.asarray(a, float), np.asarray(b, float)
        d = b - a
        mid = (a + b) / 2
        side = np.cross(d, eye - mid)
        ln = np.linalg.norm(side)
        if ln < 1e-12:
            return np.zeros((0, 3), np.float32)
        side = side / ln * width / 2
        return strip_to_triangles(band(np.stack([a, b]), np.stack([side, side])))
