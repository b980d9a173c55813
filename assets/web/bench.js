// In-page measurement of the live path's per-frame cost: decode one MESH frame
// (protocol.decodeMesh: header, zlib inflate by DecompressionStream, row-delta sum) and upload it to the GPU
// (Renderer.uploadMesh: one texSubImage2D of the uint16 grid). tools/web_bench.py feeds
// it MESH frames made by the Python encoder and writes docs/benchmarks/browser.md.
//
// performance.now() is coarsened (to 100 us in a page that is not cross-origin isolated),
// so each frame is timed over `batch` repetitions and divided.

import { decodeMesh } from "./protocol.js";
import { Renderer } from "./render.js";

function fromBase64(s) {
  const bin = atob(s);
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return out;
}

function quantiles(xs) {
  const s = [...xs].sort((a, b) => a - b);
  const at = (p) => s[Math.min(s.length - 1, Math.max(0, Math.round(p * (s.length - 1))))];
  return { median: at(0.5), p95: at(0.95), min: s[0], max: s[s.length - 1], count: s.length };
}

/**
 * frames: MESH messages as base64 strings (all of one n). Returns per-stage quantiles over
 * frames of the ms per frame: decode, upload, decode+upload, and decode+upload followed by
 * gl.finish() (the upload completed in the GPU process, an upper bound).
 */
export async function benchDecodeUpload(frames, { batch = 10, repeats = 5 } = {}) {
  const canvas = document.createElement("canvas");
  canvas.width = 64; canvas.height = 64;
  const r = new Renderer(canvas);
  const gl = r.gl;
  const bytes = frames.map(fromBase64);
  // warm up: compile paths, allocate the texture
  for (const b of bytes) r.uploadMesh(await decodeMesh(b));
  gl.finish();
  const decode = [], upload = [], both = [], finished = [];
  // Each stage of each frame: the mean over `batch` runs, best of `repeats` such means
  // (a time slice lost to another process only ever adds time).
  // Decoding is asynchronous (DecompressionStream): a run is awaited whole.
  const best = async (fn) => {
    let m = Infinity;
    for (let r = 0; r < repeats; r++) {
      gl.finish();
      const t = performance.now();
      await fn();
      m = Math.min(m, (performance.now() - t) / batch);
    }
    return m;
  };
  for (const b of bytes) {
    const m = await decodeMesh(b);
    decode.push(await best(async () => { for (let k = 0; k < batch; k++) await decodeMesh(b); }));
    upload.push(await best(() => { for (let k = 0; k < batch; k++) r.uploadMesh(m); }));
    both.push(await best(async () => {
      for (let k = 0; k < batch; k++) r.uploadMesh(await decodeMesh(b));
    }));
    finished.push(await best(async () => {
      for (let k = 0; k < batch; k++) { r.uploadMesh(await decodeMesh(b)); gl.finish(); }
    }));
  }
  const n = (await decodeMesh(bytes[0])).n;
  const ext = gl.getExtension("WEBGL_debug_renderer_info");
  const renderer = ext ? gl.getParameter(ext.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
  const sizes = bytes.map((b) => b.length);
  r.gl.getExtension("WEBGL_lose_context")?.loseContext();
  return {
    n, frames: bytes.length, batch, repeats, renderer, userAgent: navigator.userAgent,
    bytes: quantiles(sizes),
    decode: quantiles(decode), upload: quantiles(upload),
    decodeUpload: quantiles(both), decodeUploadFinish: quantiles(finished),
  };
}
