// DEFLATE (RFC 1951) decoder with zlib (RFC 1950) and gzip (RFC 1952) wrappers.
//
// Synchronous and dependency-free, so the page needs no CDN and no build step, and a mesh
// frame is decoded in one call (the browser's DecompressionStream is asynchronous).
// Every malformed input throws an InflateError; output is never allowed to grow past the
// caller's limit (a MESH frame knows its exact size in advance).

export class InflateError extends Error {}

const LBASE = new Uint16Array([3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 15, 17, 19, 23, 27, 31, 35, 43,
  51, 59, 67, 83, 99, 115, 131, 163, 195, 227, 258]);
const LEXT = new Uint8Array([0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 4, 4,
  4, 4, 5, 5, 5, 5, 0]);
const DBASE = new Uint16Array([1, 2, 3, 4, 5, 7, 9, 13, 17, 25, 33, 49, 65, 97, 129, 193, 257,
  385, 513, 769, 1025, 1537, 2049, 3073, 4097, 6145, 8193, 12289, 16385, 24577]);
const DEXT = new Uint8Array([0, 0, 0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7, 8, 8, 9, 9,
  10, 10, 11, 11, 12, 12, 13, 13]);
const CLORDER = [16, 17, 18, 0, 8, 7, 9, 6, 10, 5, 11, 4, 12, 3, 13, 2, 14, 1, 15];

// A Huffman code as a single-level lookup table indexed by the next `bits` input bits
// (LSB first): entry = symbol << 4 | code length, or 0 for a bit pattern no code starts with.
function buildTable(lengths, count) {
  let max = 0;
  const bl = new Uint16Array(16);
  for (let i = 0; i < count; i++) {
    const l = lengths[i];
    bl[l]++;
    if (l > max) max = l;
  }
  if (max === 0) return { table: new Uint16Array(2), bits: 1 };
  bl[0] = 0;
  const next = new Uint16Array(16);
  let code = 0;
  let left = 1;
  for (let b = 1; b <= 15; b++) {
    code = (code + bl[b - 1]) << 1;
    next[b] = code;
    left = (left << 1) - bl[b];
    if (left < 0) throw new InflateError("invalid deflate stream: over-subscribed Huffman code");
  }
  const size = 1 << max;
  const table = new Uint16Array(size); // 16-bit entries: half the cache footprint
  for (let sym = 0; sym < count; sym++) {
    const len = lengths[sym];
    if (!len) continue;
    let c = next[len]++;
    let rev = 0;
    for (let k = 0; k < len; k++) { rev = (rev << 1) | (c & 1); c >>= 1; }
    const entry = (sym << 4) | len;
    for (let k = rev; k < size; k += 1 << len) table[k] = entry;
  }
  return { table, bits: max };
}

let FIXED_L = null;
let FIXED_D = null;
function fixedTables() {
  if (!FIXED_L) {
    const l = new Uint8Array(288);
    l.fill(8, 0, 144); l.fill(9, 144, 256); l.fill(7, 256, 280); l.fill(8, 280, 288);
    FIXED_L = buildTable(l, 288);
    FIXED_D = buildTable(new Uint8Array(30).fill(5), 30);
  }
  return [FIXED_L, FIXED_D];
}

// A bigger output buffer (a top-level function: a closure over the decoder's locals would
// make V8 keep them in a heap context and slow the hot loop several times over).
function grow(buf, op, need, cap, fixed) {
  if (need > cap || fixed) throw new InflateError(`inflated data larger than ${cap} bytes`);
  const nb = new Uint8Array(Math.min(cap, Math.max(need, buf.length * 2)));
  nb.set(buf.subarray(0, op));
  return nb;
}

/**
 * Raw DEFLATE data starting at `start` of `src` (a Uint8Array).
 * `out`: a preallocated Uint8Array whose exact size is known (decoding more is an error,
 * decoding less is reported through the returned length), or null to grow up to `limit`.
 * Returns { out, length, end } where `end` is the input offset after the last block.
 */
export function inflateRaw(src, start = 0, out = null, limit = 1 << 30) {
  let buf = out || new Uint8Array(Math.min(limit, Math.max(1024, src.length * 4)));
  const cap = out ? out.length : limit;
  let op = 0;
  let pos = start;
  const end = src.length;
  let bb = 0; // bit buffer
  let bc = 0; // bits in it
  let overrun = 0; // zero bytes fed past the end of the input

  const fixed = out !== null;

  let last = 0;
  while (!last) {
    while (bc < 3) { if (pos < end) bb |= src[pos++] << bc; else overrun++; bc += 8; }
    last = bb & 1;
    const type = (bb >>> 1) & 3;
    bb >>>= 3; bc -= 3;
    if (type === 0) {
      // To a byte boundary: drop the partial byte; whole bytes read ahead go back.
      if (overrun) throw new InflateError("deflate stream truncated (stored block)");
      pos -= bc >>> 3;
      bb = 0; bc = 0;
      if (pos + 4 > end) throw new InflateError("deflate stream truncated (stored block)");
      const len = src[pos] | (src[pos + 1] << 8);
      const nlen = src[pos + 2] | (src[pos + 3] << 8);
      pos += 4;
      if ((len ^ 0xffff) !== nlen) throw new InflateError("invalid deflate stored block length");
      if (pos + len > end) throw new InflateError("deflate stream truncated (stored block)");
      if (op + len > buf.length) buf = grow(buf, op, op + len, cap, fixed);
      buf.set(src.subarray(pos, pos + len), op);
      op += len; pos += len;
      continue;
    }
    let lt, dt;
    if (type === 1) {
      [lt, dt] = fixedTables();
    } else if (type === 2) {
      while (bc < 14) { if (pos < end) bb |= src[pos++] << bc; else overrun++; bc += 8; }
      const hlit = (bb & 31) + 257;
      const hdist = ((bb >>> 5) & 31) + 1;
      const hclen = ((bb >>> 10) & 15) + 4;
      bb >>>= 14; bc -= 14;
      if (hlit > 286 || hdist > 30) throw new InflateError("invalid deflate code counts");
      const cl = new Uint8Array(19);
      for (let i = 0; i < hclen; i++) {
        while (bc < 3) { if (pos < end) bb |= src[pos++] << bc; else overrun++; bc += 8; }
        cl[CLORDER[i]] = bb & 7;
        bb >>>= 3; bc -= 3;
      }
      const ct = buildTable(cl, 19);
      const lens = new Uint8Array(hlit + hdist);
      let i = 0;
      while (i < hlit + hdist) {
        while (bc < 16) { if (pos < end) bb |= src[pos++] << bc; else overrun++; bc += 8; }
        const e = ct.table[bb & ((1 << ct.bits) - 1)];
        if (!e) throw new InflateError("invalid deflate code-length code");
        const l = e & 15;
        const sym = e >>> 4;
        bb >>>= l; bc -= l;
        if (sym < 16) { lens[i++] = sym; continue; }
        let rep, val = 0;
        if (sym === 16) {
          if (i === 0) throw new InflateError("invalid deflate repeat with no previous length");
          val = lens[i - 1]; rep = 3 + (bb & 3); bb >>>= 2; bc -= 2;
        } else if (sym === 17) {
          rep = 3 + (bb & 7); bb >>>= 3; bc -= 3;
        } else {
          rep = 11 + (bb & 127); bb >>>= 7; bc -= 7;
        }
        if (i + rep > hlit + hdist) throw new InflateError("invalid deflate code lengths");
        lens.fill(val, i, i + rep); i += rep;
      }
      if (!lens[256]) throw new InflateError("invalid deflate block: no end-of-block code");
      lt = buildTable(lens.subarray(0, hlit), hlit);
      dt = buildTable(lens.subarray(hlit), hdist);
    } else {
      throw new InflateError("invalid deflate block type 3");
    }
    const ltab = lt.table, lmask = (1 << lt.bits) - 1;
    const dtab = dt.table, dmask = (1 << dt.bits) - 1;
    const safe = end - 4;
    for (;;) {
      if (bc < 15) {
        if (pos < safe) { // fast refill: two bytes, no bounds checks
          bb |= (src[pos] << bc) | (src[pos + 1] << (bc + 8));
          pos += 2; bc += 16;
        } else {
          while (bc < 15) { if (pos < end) bb |= src[pos++] << bc; else overrun++; bc += 8; }
        }
      }
      const e = ltab[bb & lmask];
      if (!e) throw new InflateError("invalid deflate literal/length code");
      const l = e & 15;
      let sym = e >>> 4;
      bb >>>= l; bc -= l;
      if (sym < 256) {
        if (op >= buf.length) buf = grow(buf, op, op + 1, cap, fixed);
        buf[op++] = sym;
        continue;
      }
      if (sym === 256) break;
      sym -= 257;
      if (sym >= 29) throw new InflateError("invalid deflate length symbol");
      let len = LBASE[sym];
      const lx = LEXT[sym];
      if (lx) {
        while (bc < lx) { if (pos < end) bb |= src[pos++] << bc; else overrun++; bc += 8; }
        len += bb & ((1 << lx) - 1); bb >>>= lx; bc -= lx;
      }
      while (bc < 15) { if (pos < end) bb |= src[pos++] << bc; else overrun++; bc += 8; }
      const de = dtab[bb & dmask];
      if (!de) throw new InflateError("invalid deflate distance code");
      const dl = de & 15;
      const dsym = de >>> 4;
      bb >>>= dl; bc -= dl;
      if (dsym >= 30) throw new InflateError("invalid deflate distance symbol");
      let dist = DBASE[dsym];
      const dx = DEXT[dsym];
      if (dx) {
        while (bc < dx) { if (pos < end) bb |= src[pos++] << bc; else overrun++; bc += 8; }
        dist += bb & ((1 << dx) - 1); bb >>>= dx; bc -= dx;
      }
      if (dist > op) throw new InflateError("invalid deflate distance: before the start");
      if (op + len > buf.length) buf = grow(buf, op, op + len, cap, fixed);
      let from = op - dist;
      if (len > 64 && dist >= len) { // long copies: the builtin; short ones: a loop
        buf.copyWithin(op, from, from + len);
        op += len;
      } else {
        const stop = op + len;
        while (op < stop) buf[op++] = buf[from++];
      }
    }
    if (overrun * 8 > bc) throw new InflateError("deflate stream truncated");
  }
  if (overrun * 8 > bc) throw new InflateError("deflate stream truncated");
  // Give back the whole bytes read ahead into the bit buffer.
  const unread = (bc >>> 3) - overrun;
  return { out: buf, length: op, end: pos - Math.max(0, unread) };
}

function adler32(data, length) {
  let a = 1, b = 0;
  let i = 0;
  while (i < length) {
    const stop = Math.min(length, i + 3800);
    for (; i < stop; i++) { a += data[i]; b += a; }
    a %= 65521; b %= 65521;
  }
  return ((b << 16) | a) >>> 0;
}

/** A zlib stream -> Uint8Array. `expected`: the exact decoded size when known (else limit). */
export function inflateZlib(src, expected = -1, limit = 1 << 30) {
  if (src.length < 6) throw new InflateError("zlib stream too short");
  const cmf = src[0], flg = src[1];
  if ((cmf & 15) !== 8 || (cmf >>> 4) > 7) throw new InflateError("not a zlib stream (method)");
  if (((cmf << 8) | flg) % 31 !== 0) throw new InflateError("not a zlib stream (header check)");
  if (flg & 32) throw new InflateError("zlib preset dictionaries are not supported");
  const out = expected >= 0 ? new Uint8Array(expected) : null;
  const r = inflateRaw(src, 2, out, expected >= 0 ? expected : limit);
  if (r.end + 4 > src.length) throw new InflateError("zlib stream truncated (checksum)");
  const p = r.end;
  const want = ((src[p] << 24) | (src[p + 1] << 16) | (src[p + 2] << 8) | src[p + 3]) >>> 0;
  if (adler32(r.out, r.length) !== want) throw new InflateError("zlib checksum mismatch");
  if (expected >= 0 && r.length !== expected) {
    throw new InflateError(`zlib data of ${r.length} bytes, need ${expected}`);
  }
  return r.out.subarray(0, r.length);
}

let CRC = null;
function crc32(data, length) {
  if (!CRC) {
    CRC = new Int32Array(256);
    for (let n = 0; n < 256; n++) {
      let c = n;
      for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
      CRC[n] = c;
    }
  }
  let c = -1;
  for (let i = 0; i < length; i++) c = CRC[(c ^ data[i]) & 255] ^ (c >>> 8);
  return (c ^ -1) >>> 0;
}

/** A gzip file (one or more members) -> Uint8Array. */
export function gunzip(src, limit = 1 << 30) {
  const parts = [];
  let total = 0;
  let p = 0;
  while (p < src.length) {
    if (src.length - p < 18 || src[p] !== 0x1f || src[p + 1] !== 0x8b || src[p + 2] !== 8) {
      if (parts.length) break; // trailing padding after a member
      throw new InflateError("not a gzip stream");
    }
    const flg = src[p + 3];
    let q = p + 10;
    if (flg & 4) q += 2 + (src[q] | (src[q + 1] << 8));
    if (flg & 8) { while (q < src.length && src[q]) q++; q++; }
    if (flg & 16) { while (q < src.length && src[q]) q++; q++; }
    if (flg & 2) q += 2;
    if (q >= src.length) throw new InflateError("gzip header truncated");
    const r = inflateRaw(src, q, null, limit - total);
    const t = r.end;
    if (t + 8 > src.length) throw new InflateError("gzip stream truncated (trailer)");
    const crc = (src[t] | (src[t + 1] << 8) | (src[t + 2] << 16) | (src[t + 3] << 24)) >>> 0;
    const isize = (src[t + 4] | (src[t + 5] << 8) | (src[t + 6] << 16) | (src[t + 7] << 24)) >>> 0;
    if (crc32(r.out, r.length) !== crc) throw new InflateError("gzip checksum mismatch");
    if (isize !== r.length >>> 0) throw new InflateError("gzip length mismatch");
    parts.push(r.out.subarray(0, r.length));
    total += r.length;
    p = t + 8;
  }
  if (parts.length === 1) return parts[0];
  const all = new Uint8Array(total);
  let o = 0;
  for (const part of parts) { all.set(part, o); o += part.length; }
  return all;
}
