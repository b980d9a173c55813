// The clothball wire protocol, browser side: the decoders of server/protocol.py, field for
// field (docs/protocol.md documents it). JSON control messages are plain JSON text; binary
// frames start with the same 16-byte little-endian header:
//
//   offset 0  u8   type     HIP=1, CORNER=2, MESH=3, TRACK=4
//   offset 1  u8   version  the message's format: 1 (MESH: 2; MESH 1 still read)
//   offset 2  u16  flags    MESH: bit 0 zlib payload, bit 1 row-delta payload
//   offset 4  u32  seq      sender's sequence number
//   offset 8  f64  time     sender's clock, seconds
//
// Every decoder validates what it reads and throws a ProtocolError with the same `code`
// the Python decoder raises. tests/data/protocol_vectors.json (made by the Python encoder)
// proves the two agree.


export const PROTOCOL_VERSION = 1;
// Each binary type's format versions read (protocol.py's READ_VERSIONS): MESH 2 is sent,
// MESH 1 (interleaved payload) is still read for old replays.
export const MESH_VERSION = 2;
export const READ_VERSIONS = { 1: [1], 2: [1], 3: [1, 2], 4: [1] };
export const HIP = 1, CORNER = 2, MESH = 3, TRACK = 4;
export const BINARY_TYPES = { 1: "HIP", 2: "CORNER", 3: "MESH", 4: "TRACK" };
export const FLAG_ZLIB = 1, FLAG_DELTA = 2;
export const HEADER_SIZE = 16;
export const HIP_SIZE = HEADER_SIZE + 12;
export const CORNER_SIZE = HEADER_SIZE + 88; // <qB3x3f3f3ff3f3fId
export const MESH_BODY_SIZE = 100; // <qH2x3f3f3ff12f
export const TRACK_SIZE = HEADER_SIZE + 128; // <q3f3f12f12f
export const MAX_MESH_N = 1024;
export const QMAX = 65535;

const LITTLE_ENDIAN = new Uint8Array(new Uint16Array([1]).buffer)[0] === 1;

export class ProtocolError extends Error {
  constructor(code, message) {
    super(message);
    this.code = code;
    this.name = "ProtocolError";
  }
}

/** Anything binary (ArrayBuffer, a typed array, a DataView) -> Uint8Array view. */
export function asBytes(data) {
  if (data instanceof Uint8Array) return data;
  if (data instanceof ArrayBuffer) return new Uint8Array(data);
  if (ArrayBuffer.isView(data)) return new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
  throw new TypeError("expected binary data");
}

function view(bytes) {
  return new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
}

function int64(dv, off) {
  return Number(dv.getBigInt64(off, true));
}

function f32s(dv, off, count) {
  const out = new Array(count);
  for (let i = 0; i < count; i++) out[i] = dv.getFloat32(off + 4 * i, true);
  return out;
}

function triples(flat) {
  const out = [];
  for (let i = 0; i < flat.length; i += 3) out.push(flat.slice(i, i + 3));
  return out;
}

export function decodeHeader(data, expect = null) {
  const b = asBytes(data);
  if (b.length < HEADER_SIZE) {
    throw new ProtocolError("bad_binary", `binary message of ${b.length} bytes; header is 16`);
  }
  const dv = view(b);
  const type = dv.getUint8(0), version = dv.getUint8(1), flags = dv.getUint16(2, true);
  const seq = dv.getUint32(4, true), time = dv.getFloat64(8, true);
  if (!(type in BINARY_TYPES)) throw new ProtocolError("bad_binary", `unknown binary message type ${type}`);
  if (!READ_VERSIONS[type].includes(version)) {
    throw new ProtocolError("bad_version",
      `${BINARY_TYPES[type]} message version ${version}; this side reads ${READ_VERSIONS[type].join(", ")}`);
  }
  if (expect !== null && type !== expect) {
    throw new ProtocolError("bad_binary",
      `expected a ${BINARY_TYPES[expect]} message, got ${BINARY_TYPES[type]}`);
  }
  if (!Number.isFinite(time)) throw new ProtocolError("bad_binary", "header time must be finite");
  return { type, version, flags, seq, time };
}

export function decodeHip(data) {
  const b = asBytes(data);
  if (b.length !== HIP_SIZE) {
    throw new ProtocolError("bad_binary", `HIP message must be ${HIP_SIZE} bytes, got ${b.length}`);
  }
  const h = decodeHeader(b, HIP);
  const position = f32s(view(b), HEADER_SIZE, 3);
  if (!position.every(Number.isFinite)) {
    throw new ProtocolError("bad_binary", "HIP position must be finite (got NaN or Inf)");
  }
  return { kind: "HIP", position, seq: h.seq, time: h.time };
}

export function decodeCorner(data) {
  const b = asBytes(data);
  if (b.length !== CORNER_SIZE) {
    throw new ProtocolError("bad_binary",
      `CORNER message must be ${CORNER_SIZE} bytes, got ${b.length}`);
  }
  const h = decodeHeader(b, CORNER);
  if (h.flags) throw new ProtocolError("bad_binary", `CORNER unknown flags 0x${h.flags.toString(16)}`);
  const dv = view(b);
  const o = HEADER_SIZE;
  const f = f32s(dv, o + 12, 16);
  return {
    kind: "CORNER",
    frame: int64(dv, o),
    seat: dv.getUint8(o + 8),
    position: f.slice(0, 3),
    velocity: f.slice(3, 6),
    force: f.slice(6, 9),
    stiffness: f[9],
    ballPosition: f.slice(10, 13),
    ballVelocity: f.slice(13, 16),
    hipSeq: dv.getUint32(o + 76, true),
    hipTime: dv.getFloat64(o + 80, true),
    serverTime: h.time,
  };
}

/** A compressed payload that cannot be inflated, or inflates past its limit. */
export class InflateError extends Error {}

/**
 * Inflate a zlib (`format` "deflate") or gzip ("gzip") stream with the browser's own
 * DecompressionStream. At most `limit` bytes come out: a larger output is refused (a MESH
 * frame knows its exact size, a replay file its cap), as is a damaged or truncated stream.
 */
export async function inflate(bytes, format, limit) {
  const reader = new Blob([bytes]).stream().pipeThrough(new DecompressionStream(format)).getReader();
  const chunks = [];
  let size = 0;
  try {
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      size += value.length;
      if (size > limit) {
        reader.cancel().catch(() => {});
        throw new InflateError(`inflated data larger than ${limit} bytes`);
      }
      chunks.push(value);
    }
  } catch (e) {
    if (e instanceof InflateError) throw e;
    throw new InflateError(`invalid ${format} stream: ${e.message || e}`);
  }
  if (chunks.length === 1) return chunks[0];
  const out = new Uint8Array(size);
  let o = 0;
  for (const c of chunks) { out.set(c, o); o += c.length; }
  return out;
}

/**
 * A MESH frame (asynchronous: the payload is inflated by the browser's DecompressionStream;
 * a caller that applies frames must keep them in order, see app.js). The positions stay quantised (`q`: Uint16Array of n*n*3, row-major
 * [i][j][xyz]) so the renderer can upload them as they are and dequantise on the GPU;
 * `meshPositions(mesh)` gives the float64 positions exactly as the Python decoder does.
 */
export async function decodeMesh(data) {
  const b = asBytes(data);
  const h = decodeHeader(b, MESH);
  if (b.length < HEADER_SIZE + MESH_BODY_SIZE) throw new ProtocolError("bad_binary", "MESH message too short");
  const dv = view(b);
  const o = HEADER_SIZE;
  const frame = int64(dv, o);
  const n = dv.getUint16(o + 8, true);
  if (!(n >= 2 && n <= MAX_MESH_N)) {
    throw new ProtocolError("bad_binary", `MESH n must be 2..${MAX_MESH_N}, got ${n}`);
  }
  const f = f32s(dv, o + 12, 22);
  if (h.flags & ~(FLAG_ZLIB | FLAG_DELTA)) {
    throw new ProtocolError("bad_binary", `MESH unknown flags 0x${h.flags.toString(16)}`);
  }
  const count = n * n * 3;
  const expected = count * 2;
  let payload = b.subarray(HEADER_SIZE + MESH_BODY_SIZE);
  if (h.flags & FLAG_ZLIB) {
    try {
      payload = await inflate(payload, "deflate", expected);
    } catch (e) {
      if (!(e instanceof InflateError)) throw e;
      throw new ProtocolError("bad_binary", `MESH payload not valid zlib: ${e.message}`);
    }
  }
  if (payload.length !== expected) {
    throw new ProtocolError("bad_binary", `MESH payload of ${payload.length} bytes, need ${expected}`);
  }
  let q;
  if (h.version === 2) {
    q = meshFromPlanes(payload, n, h.flags & FLAG_DELTA);
  } else if (LITTLE_ENDIAN && payload.byteOffset % 2 === 0 && (h.flags & FLAG_ZLIB)) {
    q = new Uint16Array(payload.buffer, payload.byteOffset, count); // freshly inflated: ours
  } else if (LITTLE_ENDIAN) {
    q = new Uint16Array(count); // a copy: the caller's buffer stays untouched
    new Uint8Array(q.buffer).set(payload);
  } else {
    q = new Uint16Array(count);
    const pv = view(payload);
    for (let i = 0; i < count; i++) q[i] = pv.getUint16(2 * i, true);
  }
  if (h.version === 1 && (h.flags & FLAG_DELTA)) {
    // Rows were delta-coded along j (axis 1) with uint16 wrap-around: a cumulative sum.
    const row = n * 3;
    for (let r = 0; r < count; r += row) {
      for (let k = r + 3, stop = r + row; k < stop; k++) q[k] = q[k] + q[k - 3];
    }
  }
  return {
    kind: "MESH",
    frame,
    serverTime: h.time,
    n,
    q,
    lo: f.slice(0, 3),
    hi: f.slice(3, 6),
    ballPosition: f.slice(6, 9),
    ballRadius: f[9],
    hips: triples(f.slice(10, 22)),
    flags: h.flags,
    version: h.version,
  };
}

/**
 * MESH version 2's payload (docs/protocol.md, "MESH") to quantised nodes: byte planes (for
 * each axis its values' low bytes, then their high bytes) back to x y z a node; with
 * `predicted`, each value a zigzag-mapped residual: unmapped, then summed down the columns
 * (the row deltas) and along the rows (the nodes), wrapping as uint16.
 */
function meshFromPlanes(payload, n, predicted) {
  const nodes = n * n, q = new Uint16Array(3 * nodes);
  for (let a = 0; a < 3; a++) {
    const lo = 2 * a * nodes, hi = lo + nodes;
    for (let k = 0; k < nodes; k++) {
      const z = payload[lo + k] | (payload[hi + k] << 8);
      q[3 * k + a] = predicted ? (z >>> 1) ^ -(z & 1) : z; // Uint16Array keeps the low 16 bits
    }
  }
  if (predicted) {
    const row = 3 * n;
    for (let k = row; k < q.length; k++) q[k] = q[k] + q[k - row];
    for (let r = 0; r < q.length; r += row) {
      for (let k = r + 3, stop = r + row; k < stop; k++) q[k] = q[k] + q[k - 3];
    }
  }
  return q;
}

/** Float64Array(n*n*3): lo + q * ((hi - lo) / 65535), the same arithmetic as Python. */
export function meshPositions(mesh) {
  const { q, lo, hi } = mesh;
  const out = new Float64Array(q.length);
  const s = [(hi[0] - lo[0]) / QMAX, (hi[1] - lo[1]) / QMAX, (hi[2] - lo[2]) / QMAX];
  for (let i = 0; i < q.length; i += 3) {
    out[i] = lo[0] + q[i] * s[0];
    out[i + 1] = lo[1] + q[i + 1] * s[1];
    out[i + 2] = lo[2] + q[i + 2] * s[2];
  }
  return out;
}

/** One node's dequantised position. */
export function meshNode(mesh, i, j) {
  const k = (i * mesh.n + j) * 3;
  const { q, lo, hi } = mesh;
  return [0, 1, 2].map((c) => lo[c] + q[k + c] * ((hi[c] - lo[c]) / QMAX));
}

export function decodeTrack(data) {
  const b = asBytes(data);
  if (b.length !== TRACK_SIZE) {
    throw new ProtocolError("bad_binary", `TRACK message must be ${TRACK_SIZE} bytes`);
  }
  const h = decodeHeader(b, TRACK);
  if (h.flags) throw new ProtocolError("bad_binary", `TRACK unknown flags 0x${h.flags.toString(16)}`);
  const dv = view(b);
  const f = f32s(dv, HEADER_SIZE + 8, 30);
  return {
    kind: "TRACK",
    frame: int64(dv, HEADER_SIZE),
    serverTime: h.time,
    ballPosition: f.slice(0, 3),
    ballVelocity: f.slice(3, 6),
    hips: triples(f.slice(6, 18)),
    corners: triples(f.slice(18, 30)),
  };
}

/** Any binary message; a promise, since a MESH is inflated asynchronously. */
export async function decodeBinary(data) {
  const h = decodeHeader(data);
  return { 1: decodeHip, 2: decodeCorner, 3: decodeMesh, 4: decodeTrack }[h.type](data);
}

/** A control message: a JSON object with a string `type`. */
export function decodeJson(text) {
  let msg;
  try {
    msg = JSON.parse(text);
  } catch (e) {
    throw new ProtocolError("bad_json", `not valid JSON: ${e.message}`);
  }
  if (msg === null || typeof msg !== "object" || Array.isArray(msg)) {
    throw new ProtocolError("bad_json", "expected a JSON object");
  }
  if (typeof msg.type !== "string" || !msg.type) {
    throw new ProtocolError("bad_message", "missing field 'type' (a string)");
  }
  return msg;
}

export function hello(fields = {}) {
  return JSON.stringify({ type: "hello", version: PROTOCOL_VERSION, ...fields });
}
