// WebGL2 renderer of a clothball scene: the cloth (lit with per-vertex normals, each
// guarded edge tinted with its player's colour), the ball, a marker at each corner, each
// player's hand with a line to its corner (the pull), and a floor grid.
//
// The cloth's positions go to the GPU exactly as they arrive: the MESH frame's uint16
// grid is uploaded as an RGB16UI texture (one texSubImage2D call) and the vertex shader
// dequantises it with the frame's bounding box and computes each normal from the four
// neighbours (central differences). So the CPU's work per mesh frame is the decode and one
// copy, and normals are computed only for frames that are drawn.

import { multiply } from "./camera.js";

export function hexColor(hex) {
  const v = parseInt(hex.slice(1), 16);
  return [((v >> 16) & 255) / 255, ((v >> 8) & 255) / 255, (v & 255) / 255];
}

// The one palette of both clients (the desktop window reads the same file).
export const PALETTE = await (await fetch(new URL("./palette.json", import.meta.url))).json();
export const SEAT_COLORS = PALETTE.seats;
const CLOTH_FRONT = hexColor(PALETTE.cloth_front);
const CLOTH_BACK = hexColor(PALETTE.cloth_back);
const BALL = hexColor(PALETTE.ball);
const UNGUARDED = hexColor(PALETTE.unguarded);
const BACKGROUND = hexColor(PALETTE.background);
const FLOOR_LINES = hexColor(PALETTE.floor_lines);

const CLOTH_VS = `#version 300 es
precision highp float;
precision highp int;
uniform highp usampler2D uPosA;  // the frame shown
uniform highp usampler2D uPosB;  // the next frame (replays blend towards it by uAlpha)
uniform int uN;
uniform vec3 uLoA;
uniform vec3 uScaleA;
uniform vec3 uLoB;
uniform vec3 uScaleB;
uniform float uAlpha;
uniform mat4 uVP;
out vec3 vNormal;
out vec3 vWorld;
out vec2 vUV;
vec3 node(ivec2 c) {
  c = clamp(c, ivec2(0), ivec2(uN - 1));
  vec3 a = uLoA + vec3(texelFetch(uPosA, c, 0).xyz) * uScaleA;
  if (uAlpha <= 0.0) return a;
  vec3 b = uLoB + vec3(texelFetch(uPosB, c, 0).xyz) * uScaleB;
  return mix(a, b, uAlpha);
}
void main() {
  ivec2 c = ivec2(gl_VertexID % uN, gl_VertexID / uN);  // x: column j, y: row i
  vec3 p = node(c);
  vec3 dx = node(c + ivec2(1, 0)) - node(c - ivec2(1, 0));
  vec3 dz = node(c + ivec2(0, 1)) - node(c - ivec2(0, 1));
  vec3 nrm = cross(dz, dx);
  float l = length(nrm);
  vNormal = l > 1e-20 ? nrm / l : vec3(0.0, 1.0, 0.0);
  vWorld = p;
  vUV = vec2(c) / float(uN - 1);
  gl_Position = uVP * vec4(p, 1.0);
}`;

const CLOTH_FS = `#version 300 es
precision highp float;
in vec3 vNormal;
in vec3 vWorld;
in vec2 vUV;
uniform vec3 uEye;
uniform vec3 uLight;
uniform vec3 uColor;
uniform vec3 uBack;
uniform vec4 uEdge[4];
uniform float uBand;
out vec4 outColor;
void main() {
  vec3 n = normalize(vNormal);
  vec3 v = normalize(uEye - vWorld);
  vec3 base = uColor;
  if (dot(n, v) < 0.0) { n = -n; base = uBack; }  // both sides lit, the underside darker
  float chk = mod(floor(vUV.x * 12.0) + floor(vUV.y * 12.0), 2.0);
  base *= 0.94 + 0.06 * chk;
  // edge e runs from corner e to corner e+1: north i=0, east j=n-1, south i=n-1, west j=0
  float d[4] = float[4](vUV.y, 1.0 - vUV.x, 1.0 - vUV.y, vUV.x);
  for (int e = 0; e < 4; e++) {
    float w = (1.0 - smoothstep(0.55 * uBand, uBand, d[e])) * uEdge[e].a;
    base = mix(base, uEdge[e].rgb, w);
  }
  vec3 l = normalize(uLight);
  float diff = max(dot(n, l), 0.0);
  vec3 h = normalize(l + v);
  float spec = pow(max(dot(n, h), 0.0), 40.0) * 0.18;
  outColor = vec4(base * (0.3 + 0.7 * diff) + spec, 1.0);
}`;

const SOLID_VS = `#version 300 es
precision highp float;
layout(location = 0) in vec3 aPos;
uniform mat4 uVP;
uniform vec3 uCenter;
uniform float uRadius;
out vec3 vNormal;
out vec3 vWorld;
void main() {
  vNormal = aPos;
  vWorld = uCenter + aPos * uRadius;
  gl_Position = uVP * vec4(vWorld, 1.0);
}`;

const SOLID_FS = `#version 300 es
precision highp float;
in vec3 vNormal;
in vec3 vWorld;
uniform vec3 uEye;
uniform vec3 uLight;
uniform vec4 uColor;
out vec4 outColor;
void main() {
  vec3 n = normalize(vNormal);
  vec3 v = normalize(uEye - vWorld);
  vec3 l = normalize(uLight);
  float diff = max(dot(n, l), 0.0);
  float spec = pow(max(dot(n, normalize(l + v)), 0.0), 48.0) * 0.4;
  outColor = vec4(uColor.rgb * (0.3 + 0.7 * diff) + spec, uColor.a);
}`;

const LINE_VS = `#version 300 es
precision highp float;
layout(location = 0) in vec3 aPos;
uniform mat4 uVP;
void main() { gl_Position = uVP * vec4(aPos, 1.0); }`;

const LINE_FS = `#version 300 es
precision highp float;
uniform vec4 uColor;
out vec4 outColor;
void main() { outColor = uColor; }`;

const FLOOR_VS = `#version 300 es
precision highp float;
layout(location = 0) in vec2 aPos;
uniform mat4 uVP;
uniform float uY;
uniform float uExtent;
out vec2 vXZ;
void main() {
  vXZ = aPos * uExtent;
  gl_Position = uVP * vec4(vXZ.x, uY, vXZ.y, 1.0);
}`;

const FLOOR_FS = `#version 300 es
precision highp float;
in vec2 vXZ;
uniform float uCell;
uniform float uExtent;
uniform vec3 uBg;
uniform vec3 uLines;
out vec4 outColor;
void main() {
  vec2 g = abs(fract(vXZ / uCell - 0.5) - 0.5) / fwidth(vXZ / uCell);
  float line = 1.0 - min(min(g.x, g.y), 1.0);
  float fade = 1.0 - smoothstep(0.3 * uExtent, uExtent, length(vXZ));
  vec3 c = mix(uBg, uLines, line * fade * 0.8);
  outColor = vec4(c, 1.0);
}`;

function compile(gl, vs, fs) {
  const prog = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const sh = gl.createShader(type);
    gl.shaderSource(sh, src);
    gl.compileShader(sh);
    if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) {
      throw new Error(`shader: ${gl.getShaderInfoLog(sh)}`);
    }
    gl.attachShader(prog, sh);
  }
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) {
    throw new Error(`program: ${gl.getProgramInfoLog(prog)}`);
  }
  const uniforms = {};
  const count = gl.getProgramParameter(prog, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < count; i++) {
    const name = gl.getActiveUniform(prog, i).name.replace(/\[0\]$/, "");
    uniforms[name] = gl.getUniformLocation(prog, name);
  }
  return { prog, u: uniforms };
}

function sphere(rings = 16, segments = 24) {
  const pos = [];
  const idx = [];
  for (let r = 0; r <= rings; r++) {
    const th = (r / rings) * Math.PI;
    for (let s = 0; s <= segments; s++) {
      const ph = (s / segments) * 2 * Math.PI;
      pos.push(Math.sin(th) * Math.cos(ph), Math.cos(th), Math.sin(th) * Math.sin(ph));
    }
  }
  for (let r = 0; r < rings; r++) {
    for (let s = 0; s < segments; s++) {
      const a = r * (segments + 1) + s;
      const b = a + segments + 1;
      idx.push(a, b, a + 1, b, b + 1, a + 1);
    }
  }
  return { pos: new Float32Array(pos), idx: new Uint16Array(idx) };
}

export class Renderer {
  constructor(canvas) {
    const gl = canvas.getContext("webgl2", { antialias: true, alpha: false });
    if (!gl) throw new Error("WebGL2 is not available in this browser");
    this.canvas = canvas;
    this.gl = gl;
    this.cloth = compile(gl, CLOTH_VS, CLOTH_FS);
    this.solid = compile(gl, SOLID_VS, SOLID_FS);
    this.line = compile(gl, LINE_VS, LINE_FS);
    this.floor = compile(gl, FLOOR_VS, FLOOR_FS);

    this.emptyVao = gl.createVertexArray();
    this.clothIdx = gl.createBuffer();
    this.indexCount = 0;
    this.tex = [null, null]; // slot 0: the frame shown; slot 1: the next one (replays)
    this.slotMesh = [null, null];
    this.alpha = 0;
    this.n = 0;

    const sp = sphere();
    this.sphereVao = gl.createVertexArray();
    gl.bindVertexArray(this.sphereVao);
    const vb = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, vb);
    gl.bufferData(gl.ARRAY_BUFFER, sp.pos, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
    const ib = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, sp.idx, gl.STATIC_DRAW);
    this.sphereCount = sp.idx.length;

    this.lineVao = gl.createVertexArray();
    gl.bindVertexArray(this.lineVao);
    this.lineBuf = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.lineBuf);
    gl.bufferData(gl.ARRAY_BUFFER, 6 * 4 * 4, gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);

    this.floorVao = gl.createVertexArray();
    gl.bindVertexArray(this.floorVao);
    const fb = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, fb);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    gl.bindVertexArray(null);

    this.size = 1;
    this.floorY = 0;
    this.lo = [[0, 0, 0], [0, 0, 0]];
    this.scale = [[0, 0, 0], [0, 0, 0]];
    this.ball = null; // { position, radius }
    this.corners = null; // 4 x [x, y, z]
    this.hips = null;
    this.edges = [0, 1, 2, 3].map(() => [0, 0, 0, 0]);
    this.hasMesh = false;
    this.light = [0.35, 1.0, 0.45];
  }

  /** The room's geometry (from the `joined` message or a replay header). */
  setGeometry(geometry) {
    this.size = geometry.size || 1;
    const height = geometry.height ?? 1;
    this.floorY = height - 1.5 * this.size;
    if (geometry.n) this._ensureGrid(geometry.n);
  }

  setSeatColors(active) {
    // active[e]: is edge e guarded (a seat is taken)?
    for (let e = 0; e < 4; e++) {
      const c = hexColor(SEAT_COLORS[e]);
      this.edges[e] = [c[0], c[1], c[2], active[e] ? 1 : 0.0];
    }
  }

  _ensureGrid(n) {
    if (n === this.n) return;
    const gl = this.gl;
    this.n = n;
    for (let k = 0; k < 2; k++) {
      if (this.tex[k]) gl.deleteTexture(this.tex[k]);
      const t = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, t);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGB16UI, n, n);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
      this.tex[k] = t;
    }
    this.slotMesh = [null, null];
    const idx = new Uint32Array((n - 1) * (n - 1) * 6);
    let k = 0;
    for (let i = 0; i < n - 1; i++) {
      for (let j = 0; j < n - 1; j++) {
        const a = i * n + j;
        idx[k++] = a; idx[k++] = a + n; idx[k++] = a + 1;
        idx[k++] = a + 1; idx[k++] = a + n; idx[k++] = a + n + 1;
      }
    }
    gl.bindVertexArray(this.emptyVao);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.clothIdx);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, idx, gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    this.indexCount = idx.length;
    this.hasMesh = false;
  }

  _upload(slot, mesh) {
    const gl = this.gl;
    const n = mesh.n;
    gl.bindTexture(gl.TEXTURE_2D, this.tex[slot]);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 2);
    gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, n, n, gl.RGB_INTEGER, gl.UNSIGNED_SHORT, mesh.q);
    this.lo[slot] = mesh.lo;
    this.scale[slot] = [0, 1, 2].map((c) => (mesh.hi[c] - mesh.lo[c]) / 65535);
    this.slotMesh[slot] = mesh;
  }

  _corners(mesh) {
    const n = mesh.n;
    return [[0, 0], [0, n - 1], [n - 1, n - 1], [n - 1, 0]].map(([i, j]) => this.node(mesh, i, j));
  }

  /** Upload a decoded MESH frame (protocol.decodeMesh): one texture copy, no float work. */
  uploadMesh(mesh) {
    this._ensureGrid(mesh.n);
    this._upload(0, mesh);
    this.alpha = 0;
    this.corners = this._corners(mesh);
    this.ball = { position: mesh.ballPosition, radius: mesh.ballRadius };
    this.hips = mesh.hips;
    this.hasMesh = true;
  }

  /** Show a blend of two frames (replays between 30 Hz frames): a, then b at alpha. Each
   * frame is uploaded once, however many times it is shown. */
  showBlend(a, b, alpha) {
    this._ensureGrid(a.n);
    if (this.slotMesh[0] !== a) this._upload(0, a);
    const blend = b && b !== a && b.n === a.n && alpha > 0;
    if (blend && this.slotMesh[1] !== b) this._upload(1, b);
    this.alpha = blend ? Math.min(1, alpha) : 0;
    const ca = this._corners(a);
    this.corners = blend
      ? ca.map((p, k) => { const q = this._corners(b)[k]; return p.map((v, c) => v + (q[c] - v) * this.alpha); })
      : ca;
    this.ball = { position: a.ballPosition, radius: a.ballRadius };
    this.hips = a.hips;
    this.hasMesh = true;
  }

  /** One node's position as drawn (float32 dequantisation is close enough for labels). */
  node(mesh, i, j) {
    const k = (i * mesh.n + j) * 3;
    return [0, 1, 2].map((c) => mesh.lo[c] + mesh.q[k + c] * ((mesh.hi[c] - mesh.lo[c]) / 65535));
  }

  resize() {
    const c = this.canvas;
    const dpr = Math.min(window.devicePixelRatio || 1, 2);
    const w = Math.max(1, Math.round(c.clientWidth * dpr));
    const h = Math.max(1, Math.round(c.clientHeight * dpr));
    if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
    return [w, h];
  }

  draw(camera) {
    const gl = this.gl;
    const [w, h] = this.resize();
    camera.aspect = w / h;
    const vp = multiply(camera.projection(), camera.view());
    this.viewProjection = vp;
    const eye = camera.eye();
    gl.viewport(0, 0, w, h);
    gl.clearColor(...BACKGROUND, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.disable(gl.CULL_FACE);

    // floor
    const f = this.floor;
    gl.useProgram(f.prog);
    gl.uniformMatrix4fv(f.u.uVP, false, vp);
    gl.uniform1f(f.u.uY, this.floorY);
    gl.uniform1f(f.u.uExtent, 4 * this.size);
    gl.uniform1f(f.u.uCell, 0.25 * this.size);
    gl.uniform3fv(f.u.uBg, BACKGROUND);
    gl.uniform3fv(f.u.uLines, FLOOR_LINES);
    gl.bindVertexArray(this.floorVao);
    gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);

    if (!this.hasMesh) { gl.bindVertexArray(null); return; }

    // cloth
    const c = this.cloth;
    gl.useProgram(c.prog);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.tex[0]);
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_2D, this.tex[this.alpha > 0 ? 1 : 0]);
    gl.activeTexture(gl.TEXTURE0);
    gl.uniform1i(c.u.uPosA, 0);
    gl.uniform1i(c.u.uPosB, 1);
    gl.uniform1i(c.u.uN, this.n);
    gl.uniform3fv(c.u.uLoA, this.lo[0]);
    gl.uniform3fv(c.u.uScaleA, this.scale[0]);
    gl.uniform3fv(c.u.uLoB, this.lo[1]);
    gl.uniform3fv(c.u.uScaleB, this.scale[1]);
    gl.uniform1f(c.u.uAlpha, this.alpha);
    gl.uniformMatrix4fv(c.u.uVP, false, vp);
    gl.uniform3fv(c.u.uEye, eye);
    gl.uniform3fv(c.u.uLight, this.light);
    gl.uniform3fv(c.u.uColor, CLOTH_FRONT);
    gl.uniform3fv(c.u.uBack, CLOTH_BACK);
    gl.uniform4fv(c.u.uEdge, this.edges.flat());
    gl.uniform1f(c.u.uBand, Math.min(0.12, Math.max(1.6 / (this.n - 1), 0.035)));
    gl.bindVertexArray(this.emptyVao);
    gl.drawElements(gl.TRIANGLES, this.indexCount, gl.UNSIGNED_INT, 0);

    // ball, corner markers, hands
    const s = this.solid;
    gl.useProgram(s.prog);
    gl.uniformMatrix4fv(s.u.uVP, false, vp);
    gl.uniform3fv(s.u.uEye, eye);
    gl.uniform3fv(s.u.uLight, this.light);
    gl.bindVertexArray(this.sphereVao);
    const ballShown = this.ball && this.ball.position.every(Number.isFinite)
      && this.ball.position[1] > this.floorY + 0.5 * this.ball.radius; // gone: not drawn
    if (ballShown) {
      gl.uniform3fv(s.u.uCenter, this.ball.position);
      gl.uniform1f(s.u.uRadius, this.ball.radius);
      gl.uniform4fv(s.u.uColor, [...BALL, 1]);
      gl.drawElements(gl.TRIANGLES, this.sphereCount, gl.UNSIGNED_SHORT, 0);
    }
    for (let e = 0; e < 4; e++) {
      const col = hexColor(SEAT_COLORS[e]);
      const on = this.edges[e][3] > 0;
      gl.uniform3fv(s.u.uCenter, this.corners[e]);
      gl.uniform1f(s.u.uRadius, 0.03 * this.size);
      gl.uniform4fv(s.u.uColor, on ? [...col, 1] : [...UNGUARDED, 1]);
      gl.drawElements(gl.TRIANGLES, this.sphereCount, gl.UNSIGNED_SHORT, 0);
      if (on && this.hips) {
        gl.uniform3fv(s.u.uCenter, this.hips[e]);
        gl.uniform1f(s.u.uRadius, 0.018 * this.size);
        gl.uniform4fv(s.u.uColor, [col[0] * 0.6, col[1] * 0.6, col[2] * 0.6, 1]);
        gl.drawElements(gl.TRIANGLES, this.sphereCount, gl.UNSIGNED_SHORT, 0);
      }
    }
    if (this.hips) {
      const l = this.line;
      gl.useProgram(l.prog);
      gl.uniformMatrix4fv(l.u.uVP, false, vp);
      gl.bindVertexArray(this.lineVao);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.lineBuf);
      for (let e = 0; e < 4; e++) {
        if (!(this.edges[e][3] > 0)) continue;
        gl.bufferSubData(gl.ARRAY_BUFFER, 0, new Float32Array([...this.corners[e], ...this.hips[e]]));
        gl.uniform4fv(l.u.uColor, [...hexColor(SEAT_COLORS[e]), 1]);
        gl.drawArrays(gl.LINES, 0, 2);
      }
    }
    gl.bindVertexArray(null);
  }
}
