// A whole MESH message (docs/protocol.md, "MESH"; clothball.game.wire.protocol
// .encode_quantised_mesh makes the same message in Python): the frame loop's service
// thread encodes each due room's in one call without the interpreter lock
// (binding/loop.cpp, Loop.take_encoded) and writes it into the mesh board, so that the
// encoding of hundreds of rooms' meshes a second does not contend for Python's lock.
// Little-endian, packed: header <BBHId (type 3, version 1, flags, seq = frame mod 2^32,
// server time), body <qH2x3f3f3ff12f (frame, n, pad, box lo, box hi, ball position, ball
// radius, the four hands), then the quantised nodes (uint16, n*n*3), or their row deltas
// compressed with zlib at level 1 (flags ZLIB | DELTA) where that is at most 90 % of them.
// tests/server/test_mesh_msg.py checks it against the Python encoder.
#pragma once
#include <zlib.h>

#include <cstdint>
#include <cstring>
#include <vector>

#include "loop/corner_msg.hpp"
#include "loop/mesh_quant.hpp"

namespace cb::loop {

constexpr std::uint8_t kMeshType = 3;
constexpr std::uint16_t kFlagZlib = 1, kFlagDelta = 2;
constexpr std::size_t kMeshHeadBytes = 16 + 100;  // header and body, before the nodes

// The largest MESH of an n x n cloth (uncompressed nodes).
inline std::size_t mesh_msg_max(int n) { return kMeshHeadBytes + 6 * std::size_t(n) * std::size_t(n); }

struct MeshScratch {
  std::vector<std::uint16_t> q, delta;
  std::vector<unsigned char> z;
};

// `p`: n * n nodes (x, y, z each, row-major); `ball`: its position (3); `hips`: 12.
// Writes the message into `out` (resized to it).
inline void encode_mesh_msg(std::vector<std::uint8_t>& out, MeshScratch& s, const double* p,
                            int n, std::int64_t frame, double server_time, const double* ball,
                            double radius, const double* hips, bool compress) {
  using detail::put;
  using detail::put3f;
  const std::size_t values = 3 * std::size_t(n) * std::size_t(n);
  s.q.resize(values);
  s.delta.resize(values);
  double lo[3], hi[3];
  quantise_mesh(p, n, s.q.data(), s.delta.data(), lo, hi);
  const std::size_t raw = 2 * values;
  const unsigned char* payload = reinterpret_cast<const unsigned char*>(s.q.data());
  std::size_t bytes = raw;
  std::uint16_t flags = 0;
  if (compress) {
    uLongf zn = compressBound(uLong(raw));
    s.z.resize(zn);
    if (compress2(s.z.data(), &zn, reinterpret_cast<const Bytef*>(s.delta.data()), uLong(raw),
                  1) == Z_OK &&
        double(zn) <= 0.9 * double(raw)) {
      payload = s.z.data();
      bytes = zn;
      flags = kFlagZlib | kFlagDelta;
    }
  }
  out.resize(kMeshHeadBytes + bytes);
  std::uint8_t* w = out.data();
  w = put(w, kMeshType);
  w = put(w, kProtocolVersion);
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
