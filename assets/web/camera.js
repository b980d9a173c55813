// An orbit camera around a target (y is up), driven by pointer events: drag to orbit,
// wheel to zoom, one finger to orbit and two fingers to pinch-zoom on a touch screen.
// Matrices are column-major Float32Array(16), as WebGL expects.

export function perspective(fovy, aspect, near, far) {
  const f = 1 / Math.tan(fovy / 2);
  const m = new Float32Array(16);
  m[0] = f / aspect; m[5] = f;
  m[10] = (far + near) / (near - far); m[11] = -1;
  m[14] = (2 * far * near) / (near - far);
  return m;
}

export function lookAt(eye, target, up) {
  let zx = eye[0] - target[0], zy = eye[1] - target[1], zz = eye[2] - target[2];
  let l = Math.hypot(zx, zy, zz) || 1;
  zx /= l; zy /= l; zz /= l;
  let xx = up[1] * zz - up[2] * zy, xy = up[2] * zx - up[0] * zz, xz = up[0] * zy - up[1] * zx;
  l = Math.hypot(xx, xy, xz) || 1;
  xx /= l; xy /= l; xz /= l;
  const yx = zy * xz - zz * xy, yy = zz * xx - zx * xz, yz = zx * xy - zy * xx;
  return new Float32Array([
    xx, yx, zx, 0,
    xy, yy, zy, 0,
    xz, yz, zz, 0,
    -(xx * eye[0] + xy * eye[1] + xz * eye[2]),
    -(yx * eye[0] + yy * eye[1] + yz * eye[2]),
    -(zx * eye[0] + zy * eye[1] + zz * eye[2]),
    1,
  ]);
}

export function multiply(a, b) {
  const o = new Float32Array(16);
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      o[c * 4 + r] = a[r] * b[c * 4] + a[4 + r] * b[c * 4 + 1] + a[8 + r] * b[c * 4 + 2]
        + a[12 + r] * b[c * 4 + 3];
    }
  }
  return o;
}

export class OrbitCamera {
  constructor({ target = [0, 1, 0], distance = 2.2, yaw = 0.6, pitch = 0.75 } = {}) {
    this.target = target.slice();
    this.distance = distance;
    this.yaw = yaw; // about +y; 0 looks along -z (from +z towards the south edge's far side)
    this.pitch = pitch; // above the horizon
    this.minDistance = 0.3;
    this.maxDistance = 20;
    this.fovy = (45 * Math.PI) / 180;
    this.aspect = 1;
    this._pointers = new Map();
    this._pinch = 0;
    this.onchange = null;
  }

  /** Frame a cloth of this size hanging at this height. */
  frame(size, height) {
    this.target = [0, height - 0.1 * size, 0];
    this.distance = 2.4 * size;
    this.minDistance = 0.3 * size;
    this.maxDistance = 20 * size;
  }

  eye() {
    const cp = Math.cos(this.pitch);
    return [
      this.target[0] + this.distance * cp * Math.sin(this.yaw),
      this.target[1] + this.distance * Math.sin(this.pitch),
      this.target[2] + this.distance * cp * Math.cos(this.yaw),
    ];
  }

  view() { return lookAt(this.eye(), this.target, [0, 1, 0]); }

  projection() {
    const near = Math.max(0.01, this.distance * 0.02);
    // A portrait screen (a phone) keeps the horizontal field of view: the cloth still fits.
    const fovy = this.aspect >= 1 ? this.fovy
      : Math.min(1.9, 2 * Math.atan(Math.tan(this.fovy / 2) / this.aspect));
    return perspective(fovy, this.aspect, near, this.distance * 50);
  }

  viewProjection() { return multiply(this.projection(), this.view()); }

  orbit(dx, dy) {
    this.yaw -= dx * 0.008;
    this.pitch = Math.min(1.55, Math.max(-1.2, this.pitch + dy * 0.008));
    this._changed();
  }

  zoom(factor) {
    this.distance = Math.min(this.maxDistance, Math.max(this.minDistance, this.distance * factor));
    this._changed();
  }

  _changed() { if (this.onchange) this.onchange(this); }

  /** Listen to the canvas's pointer and wheel events. Returns a function that detaches. */
  attach(el) {
    const down = (e) => {
      try { el.setPointerCapture(e.pointerId); } catch { /* not an active pointer */ }
      this._pointers.set(e.pointerId, [e.clientX, e.clientY]);
      if (this._pointers.size === 2) this._pinch = this._spread();
    };
    const move = (e) => {
      const prev = this._pointers.get(e.pointerId);
      if (!prev) return;
      const cur = [e.clientX, e.clientY];
      this._pointers.set(e.pointerId, cur);
      if (this._pointers.size === 1) {
        this.orbit(cur[0] - prev[0], cur[1] - prev[1]);
      } else if (this._pointers.size === 2) {
        const s = this._spread();
        if (this._pinch > 0 && s > 0) this.zoom(this._pinch / s);
        this._pinch = s;
      }
      e.preventDefault();
    };
    const up = (e) => {
      this._pointers.delete(e.pointerId);
      this._pinch = this._pointers.size === 2 ? this._spread() : 0;
    };
    const wheel = (e) => {
      e.preventDefault();
      const d = e.deltaMode === 1 ? e.deltaY * 16 : e.deltaY;
      this.zoom(Math.exp(d * 0.001));
    };
    el.addEventListener("pointerdown", down);
    el.addEventListener("pointermove", move);
    el.addEventListener("pointerup", up);
    el.addEventListener("pointercancel", up);
    el.addEventListener("wheel", wheel, { passive: false });
    return () => {
      el.removeEventListener("pointerdown", down);
      el.removeEventListener("pointermove", move);
      el.removeEventListener("pointerup", up);
      el.removeEventListener("pointercancel", up);
      el.removeEventListener("wheel", wheel);
    };
  }

  _spread() {
    const [a, b] = [...this._pointers.values()];
    return Math.hypot(a[0] - b[0], a[1] - b[1]);
  }
}

/** World point -> CSS pixels in an element of this size (null: behind the camera). */
export function project(vp, p, width, height) {
  const x = vp[0] * p[0] + vp[4] * p[1] + vp[8] * p[2] + vp[12];
  const y = vp[1] * p[0] + vp[5] * p[1] + vp[9] * p[2] + vp[13];
  const w = vp[3] * p[0] + vp[7] * p[1] + vp[11] * p[2] + vp[15];
  if (w <= 1e-6) return null;
  return [(x / w * 0.5 + 0.5) * width, (1 - (y / w * 0.5 + 0.5)) * height];
}
