// Replay files (game/wire/replay.py) and their playback clock.
//
// A replay file is a gzip stream of:
//   16 bytes "CLOTHBALL-REPLAY", u32 format version, u32 header length H, H bytes of JSON
//   header, then records: u8 kind (0: event JSON text, 1: a binary protocol message, MESH or
//   TRACK), u32 length L, L bytes. All integers little-endian.
// Meshes are kept encoded and decoded when shown; tracks (ball and hands at ~100 Hz) are
// decoded once and interpolated so the ball moves smoothly between 30 Hz cloth frames.

import {
  MESH, TRACK, asBytes, decodeHeader, decodeMesh, decodeTrack, inflate,
} from "./protocol.js";

export const REPLAY_MAGIC = "CLOTHBALL-REPLAY";
export const REPLAY_VERSION = 1;

export class ReplayError extends Error {}

// The largest replay this page inflates: a longer recording is refused, not read whole.
export const MAX_REPLAY_BYTES = 1 << 30;

/** Parse a whole replay file (the bytes as downloaded): a promise of { header, records }. */
export async function parseReplay(data) {
  let body;
  try {
    body = await inflate(asBytes(data), "gzip", MAX_REPLAY_BYTES);
  } catch (e) {
    throw new ReplayError(`not a gzip stream: ${e.message}`);
  }
  const magic = new TextDecoder().decode(body.subarray(0, 16));
  if (body.length < 24 || magic !== REPLAY_MAGIC) throw new ReplayError("not a clothball replay (bad magic)");
  const dv = new DataView(body.buffer, body.byteOffset, body.byteLength);
  const version = dv.getUint32(16, true);
  if (version !== REPLAY_VERSION) {
    throw new ReplayError(`replay format ${version}, this reader knows ${REPLAY_VERSION}`);
  }
  const hlen = dv.getUint32(20, true);
  let off = 24;
  let header;
  try {
    header = JSON.parse(new TextDecoder().decode(body.subarray(off, off + hlen)));
  } catch (e) {
    throw new ReplayError(`replay header is not JSON: ${e.message}`);
  }
  off += hlen;
  const records = [];
  while (off < body.length) {
    if (off + 5 > body.length) throw new ReplayError("replay truncated in a record header");
    const kind = dv.getUint8(off);
    const len = dv.getUint32(off + 1, true);
    off += 5;
    if ((kind !== 0 && kind !== 1) || off + len > body.length) {
      throw new ReplayError("replay record damaged or truncated");
    }
    records.push({ kind, data: body.subarray(off, off + len) });
    off += len;
  }
  return { header, records };
}

function lerp(a, b, t) { return a.map((v, i) => v + (b[i] - v) * t); }

/** Index of the last item with key <= x in a sorted array (-1 if none). */
function lastAtOrBefore(items, x, key) {
  let lo = 0, hi = items.length - 1, ans = -1;
  while (lo <= hi) {
    const mid = (lo + hi) >> 1;
    if (key(items[mid]) <= x) { ans = mid; lo = mid + 1; } else hi = mid - 1;
  }
  return ans;
}

/** A parsed replay on one timeline: seconds from the first record. */
export class Replay {
  constructor({ header, records }) {
    this.header = header;
    this.frameDt = header.geometry?.frame_dt || 0.001;
    this.meshes = []; // { frame, data }
    this.tracks = []; // decoded TRACK
    this.events = []; // { frame, msg }
    const text = new TextDecoder();
    for (const r of records) {
      if (r.kind === 0) {
        const msg = JSON.parse(text.decode(r.data));
        this.events.push({ frame: msg.frame ?? 0, msg });
      } else {
        const h = decodeHeader(r.data);
        if (h.type === MESH) {
          const dv = new DataView(r.data.buffer, r.data.byteOffset + 16, 8);
          this.meshes.push({ frame: Number(dv.getBigInt64(0, true)), data: r.data });
        } else if (h.type === TRACK) {
          this.tracks.push(decodeTrack(r.data));
        }
      }
    }
    const frames = [...this.meshes, ...this.tracks].map((m) => m.frame);
    if (!frames.length) throw new ReplayError("replay has no mesh or track records");
    this.frame0 = Math.min(...frames);
    this.frame1 = Math.max(...frames);
    this.duration = (this.frame1 - this.frame0) * this.frameDt;
    this._cache = new Map();  // index -> decoded mesh, the last few
    this._wanted = [];        // indices asked for, not decoded yet, newest last
    this._decoding = null;    // the index being inflated: one at a time
    this._pumping = false;
    this._failed = new Set(); // damaged meshes, not asked for again
    this._newest = null;  // the last mesh decoded, shown while a wanted one is inflated
    this.onMesh = null;   // called when a mesh that was asked for is ready
  }

  /** Decode the first meshes, so the first picture has a cloth. */
  async ready() {
    if (this.meshes.length) await this._decode(0);
  }

  timeOf(frame) { return (frame - this.frame0) * this.frameDt; }

  frameAt(t) { return this.frame0 + t / this.frameDt; }

  /** The index of the mesh shown at time t (the newest one not after t). */
  meshIndexAt(t) {
    return Math.max(0, lastAtOrBefore(this.meshes, this.frameAt(t) + 1e-6, (m) => m.frame));
  }

  /** The decoded mesh at an index (the last few decoded are kept). Inflating is
   * asynchronous: until that mesh is ready this is the newest mesh decoded so far, and
   * `onMesh` is called once it is (`onMesh` may ask for meshes again: a mesh being inflated
   * is not asked for twice, so the page never waits on itself). */
  mesh(index) {
    const hit = this._cache.get(index);
    if (hit) return hit;
    this._want(index);
    return this._newest;
  }

  // One mesh is inflated at a time. Requests made meanwhile wait, and only the newest ones
  // are kept (the pair of one picture): a seek makes the older ones moot.
  _want(index) {
    if (index === this._decoding || this._failed.has(index)) return;
    this._wanted = [...this._wanted.filter((i) => i !== index), index].slice(-2);
    if (!this._pumping) this._pump();
  }

  async _pump() {
    this._pumping = true;
    try {
      while (this._wanted.length) {
        const index = this._wanted.shift();
        if (this._cache.has(index)) continue;
        this._decoding = index;
        try {
          await this._decode(index);
        } catch (e) {
          this._failed.add(index);
          console.warn(`replay: mesh ${index} not shown: ${e.message}`);
          continue;
        } finally {
          this._decoding = null;
        }
        this.onMesh?.();
      }
    } finally {
      this._pumping = false;
    }
  }

  async _decode(index) {
    if (this._cache.has(index)) return;
    const m = await decodeMesh(this.meshes[index].data);
    this._cache.set(index, m);
    this._newest = m;
    if (this._cache.size > 8) this._cache.delete(this._cache.keys().next().value);
  }

  /** The meshes around time t and how far t is from the first towards the second. */
  meshPairAt(t) {
    const i = this.meshIndexAt(t);
    const j = Math.min(i + 1, this.meshes.length - 1);
    const fa = this.meshes[i].frame, fb = this.meshes[j].frame;
    const alpha = fb > fa ? Math.min(1, Math.max(0, (this.frameAt(t) - fa) / (fb - fa))) : 0;
    return { i, j, alpha };
  }

  /** Ball and hands at time t, interpolated between tracks (null when there are none). */
  trackAt(t) {
    const tr = this.tracks;
    if (!tr.length) return null;
    const f = this.frameAt(t);
    const i = lastAtOrBefore(tr, f, (x) => x.frame);
    if (i < 0) return tr[0];
    if (i >= tr.length - 1) return tr[tr.length - 1];
    const a = tr[i], b = tr[i + 1];
    const w = (f - a.frame) / Math.max(1, b.frame - a.frame);
    return {
      frame: f,
      ballPosition: lerp(a.ballPosition, b.ballPosition, w),
      hips: a.hips.map((h, k) => lerp(h, b.hips[k], w)),
      corners: a.corners.map((c, k) => lerp(c, b.corners[k], w)),
    };
  }

  /** Events up to time t (inclusive), oldest first. The end of the timeline has them all:
   * an event is stamped with the room's frame when it happened, which may be a few frames
   * after the last recorded MESH or TRACK (the timeline's end). */
  eventsUntil(t) {
    const f = this.frameAt(t) + 1e-6;
    if (f >= this.frame1) return this.events.slice();
    return this.events.filter((e) => e.frame <= f);
  }

  /** Scores shown at time t: the header's final scores, less the round's points until the
   * score event has happened. */
  scoresAt(t) {
    const final = this.header.scores || [0, 0, 0, 0];
    const scored = this.eventsUntil(t).some((e) => e.msg.event === "score");
    if (scored) return final.slice();
    const scorers = new Set(this.header.scorers || []);
    return final.map((s, i) => (scorers.has(i) ? s - 1 : s));
  }
}

/** Fetch and parse a replay by id. Throws ReplayError with `status` 404 when unknown. */
export async function fetchReplay(id) {
  const r = await fetch(`/api/replays/${encodeURIComponent(id)}`);
  if (!r.ok) {
    let why = `HTTP ${r.status}`;
    try { why = (await r.json()).error || why; } catch { /* not JSON */ }
    const e = new ReplayError(why);
    e.status = r.status;
    throw e;
  }
  const replay = new Replay(await parseReplay(await r.arrayBuffer()));
  await replay.ready();
  return replay;
}

/** The playback clock: play, pause, seek, speed. `onTime(t)` is called on every change. */
export class Playback {
  constructor(duration, onTime) {
    this.duration = duration;
    this.onTime = onTime;
    this.time = 0;
    this.speed = 1;
    this.playing = false;
    this._last = null;
    this._raf = 0;
    this._tick = this._tick.bind(this);
  }

  play() {
    if (this.playing) return;
    if (this.time >= this.duration) this.time = 0;
    this.playing = true;
    this._last = performance.now();
    this._raf = requestAnimationFrame(this._tick);
    this.onTime(this.time);
  }

  pause() {
    this.playing = false;
    cancelAnimationFrame(this._raf);
    this.onTime(this.time);
  }

  toggle() { if (this.playing) this.pause(); else this.play(); }

  seek(t) {
    this.time = Math.min(this.duration, Math.max(0, t));
    this._last = performance.now();
    this.onTime(this.time);
  }

  setSpeed(s) { this.speed = s; }

  stop() { this.playing = false; cancelAnimationFrame(this._raf); }

  _tick(now) {
    if (!this.playing) return;
    const dt = Math.min(0.25, (now - this._last) / 1000);
    this._last = now;
    this.time = Math.min(this.duration, this.time + dt * this.speed);
    if (this.time >= this.duration) this.playing = false;
    this.onTime(this.time);
    if (this.playing) this._raf = requestAnimationFrame(this._tick);
  }
}
