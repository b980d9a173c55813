// A whole MESH message (docs/protocol.md, "MESH"; clothball.game.wire.protocol
// .encode_quantised_mesh makes the same message in Python): the frame loop's service
// thread encodes each due room's in one call without the interpreter lock
// (binding/loop.cpp, Loop.take_encoded) and writes it into the mesh board, so that the
// encoding of hundreds of rooms' meshes a second does not contend for Python's lock.
// Little-endian, packed: header <BBHId (type 3, version, flags, seq = frame mod 2^32, server
// time), body <qH2x3f3f3ff12f (frame, n, pad, box lo, box hi, ball position, ball radius,
// the four hands), then the payload: the quantised nodes (uint16, n*n*3), or their row
// deltas compressed at level 1 (flags ZLIB | DELTA) where that is at most 90 % of them.
// Version 2 (what the server sends) codes each value as its residual from the plane through
// its left, upper and upper-left neighbours (the row deltas less the row above's), zigzag
// mapped (0, -1, 1, -2 ... to 0, 1, 2, 3 ...), lays them out in byte planes, axis by axis
// (x's low bytes, x's high bytes, then y's, z's) and deflates them as literals, a Huffman
// code a plane (huffman_deflate.hpp), or with libdeflate's level 1 for small cloths; version 1
// (old replays; kept here as the benchmark's "before") sends row deltas interleaved x y z
// as uint16, deflated with zlib. All are zlib streams. On a smooth cloth the residuals are
// small, so their high-byte planes are nearly all zeros: ~30 % fewer bytes than version 1
// at n = 48, in ~0.2x its time (docs/benchmarks/load.md, "MESH codings").
// tests/server/test_mesh_msg.py checks it against the Python encoder and decoder.
#pragma once
#include <zlib.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <memory>
#include <vector>

#include "loop/corner_msg.hpp"
#include "loop/huffman_deflate.hpp"
#include "loop/mesh_quant.hpp"
#include "third_party/libdeflate/libdeflate.h"

namespace cb::loop {

constexpr std::uint8_t kMeshType = 3;
constexpr std::uint8_t kMeshVersion = 2;        // the planes; 1: today's interleaved uint16
// Version 2's deflater: its planes as literals, or libdeflate's level 1; kAuto (the
// server's) takes literals from kLiteralsFromNodes nodes on and libdeflate below, where the
// literal coder's six codes a message cost more than libdeflate's match search saves
// (`clothball bench --mesh --sizes 16,24,32,40,48`: the two even at n = 32-40).
enum class MeshDeflater { kAuto, kLiterals, kLibdeflate };
constexpr std::size_t kLiteralsFromNodes = 36 * 36;
constexpr std::uint16_t kFlagZlib = 1, kFlagDelta = 2;
constexpr std::size_t kMeshHeadBytes = 16 + 100;  // header and body, before the nodes

// The largest MESH of an n x n cloth (uncompressed nodes).
inline std::size_t mesh_msg_max(int n) { return kMeshHeadBytes + 6 * std::size_t(n) * std::size_t(n); }

struct DeflaterFree {
  void operator()(libdeflate_compressor* c) const { libdeflate_free_compressor(c); }
};

// One encoder thread's buffers, kept between messages (libdeflate's compressor, where
// asked for, holds ~0.5 MB of tables: made once, not a message).
struct MeshScratch {
  std::vector<std::uint16_t> q, delta;
  std::vector<unsigned char> planes, z;
  std::unique_ptr<libdeflate_compressor, DeflaterFree> deflater;
};

// Version 2's payload order: for each axis, the low bytes of all n*n values (nodes
// row-major), then their high bytes. `v`: n*n*3 interleaved uint16; with `above` (a row's
// width of values, n*3) each value less the one above it (the first row as it is), as a
// zigzag code: given the row deltas, the 2-D residuals of docs/protocol.md. One pass over
// the nodes, writing the six planes together.
inline void to_planes(const std::uint16_t* v, std::size_t nodes, unsigned char* out,
                      std::size_t above = 0) {
  unsigned char* pl[6];
  for (int k = 0; k < 6; ++k) pl[k] = out + std::size_t(k) * nodes;
  const std::size_t first = above == 0 ? nodes : std::min(nodes, above / 3);
  for (std::size_t k = 0; k < nodes; ++k) {
    for (int a = 0; a < 3; ++a) {
      std::uint16_t x = v[3 * k + std::size_t(a)];
      if (above != 0) {
        // the first row as it is; zigzag: (r << 1) ^ (r < 0 ? 0xFFFF : 0), r read as int16
        const std::uint16_t r =
            k < first ? x : std::uint16_t(x - v[3 * k + std::size_t(a) - above]);
        x = std::uint16_t(std::uint16_t(r << 1) ^ std::uint16_t(0u - (r >> 15)));
      }
      pl[2 * a][k] = static_cast<unsigned char>(x & 0xFFu);
      pl[2 * a + 1][k] = static_cast<unsigned char>(x >> 8);
    }
  }
}

// `p`: n * n nodes (x, y, z each, row-major); `ball`: its position (3); `hips`: 12.
// Writes the message into `out` (resized to it), in `version` 2 (the server's) or 1.
inline void encode_mesh_msg(std::vector<std::uint8_t>& out, MeshScratch& s, const double* p,
                            int n, std::int64_t frame, double server_time, const double* ball,
                            double radius, const double* hips, bool compress,
                            int version = kMeshVersion,
                            MeshDeflater deflater = MeshDeflater::kAuto) {
  using detail::put;
  using detail::put3f;
  const std::size_t nodes = std::size_t(n) * std::size_t(n), values = 3 * nodes;
  s.q.resize(values);
  s.delta.resize(values);
  double lo[3], hi[3];
  quantise_mesh(p, n, s.q.data(), s.delta.data(), lo, hi);
  const std::size_t raw = 2 * values;
  const unsigned char* payload = nullptr;
  std::size_t bytes = 0;
  std::uint16_t flags = 0;
  if (compress && version == 1) {
    uLongf zn = compressBound(uLong(raw));
    s.z.resize(zn);
    if (compress2(s.z.data(), &zn, reinterpret_cast<const Bytef*>(s.delta.data()), uLong(raw),
                  1) == Z_OK &&
        double(zn) <= 0.9 * double(raw)) {
      payload = s.z.data();
      bytes = zn;
      flags = kFlagZlib | kFlagDelta;
    }
  } else if (compress) {
    s.planes.resize(raw);
    to_planes(s.delta.data(), nodes, s.planes.data(), 3 * std::size_t(n));
    // The output room is 90 % of the raw nodes: a stream that does not fit is not worth it.
    s.z.resize(std::size_t(0.9 * double(raw)));
    std::size_t zn = 0;
    if (deflater == MeshDeflater::kAuto)
      deflater = nodes >= kLiteralsFromNodes ? MeshDeflater::kLiterals
                                             : MeshDeflater::kLibdeflate;
    if (deflater == MeshDeflater::kLiterals) {
      zn = huff::zlib_literals(s.planes.data(), raw, 6, s.z.data(), s.z.size());
    } else {
      if (!s.deflater) s.deflater.reset(libdeflate_alloc_compressor(1));
      if (s.deflater)
        zn = libdeflate_zlib_compress(s.deflater.get(), s.planes.data(), raw, s.z.data(),
                                      s.z.size());
    }
    if (zn != 0) {
      payload = s.z.data();
      bytes = zn;
      flags = kFlagZlib | kFlagDelta;
    }
  }
  if (payload == nullptr) {  // the quantised nodes as they are, in the version's layout
    bytes = raw;
    if (version == 1) {
      payload = reinterpret_cast<const unsigned char*>(s.q.data());
    } else {
      s.planes.resize(raw);
      to_planes(s.q.data(), nodes, s.planes.data());
      payload = s.planes.data();
    }
  }
  out.resize(kMeshHeadBytes + bytes);
  std::uint8_t* w = out.data();
  w = put(w, kMeshType);
  w = put(w, std::uint8_t(version));
  w = put(w, flags);
  w = put(w, std::uint32_t(std::uint64_t(frame) & 0xFFFFFFFFu));
  w = put(w, server_time);
  w = put(w, frame);
  w = put(w, std::uint16_t(n));
  w = put(w, std::uint16_t(0));  // pad
  w = put3f(w, lo);
  w = put3f(w, hi);
  w = put3f(w, ball);
  w = put(w, static_cast<float>(radius));
  for (int k = 0; k < 12; ++k) w = put(w, static_cast<float>(hips[k]));
  std::memcpy(w, payload, bytes);
}

}  // namespace cb::loop
