// A CORNER message (docs/protocol.md, "CORNER"; clothball.game.wire.protocol.encode_corners
// makes the same bytes in Python): the native frame loop writes each seat's into the block
// as it publishes a frame, so that the network side only sends bytes. Little-endian, packed:
// header <BBHId (type 2, version 1, flags 0, seq = frame mod 2^32, server time), then
// <qB3x3f3f3ff3f3fId (frame, seat, pad, position, velocity, force, K, ball position, ball
// velocity as float32, HIP seq echo mod 2^32, HIP time echo). tests/server/test_corner_msg.py
// checks it byte for byte against the Python encoder.
#pragma once
#include <cstdint>
#include <cstring>

namespace cb::loop {

constexpr int kCornerBytes = 104;
constexpr std::uint8_t kCornerType = 2;
constexpr std::uint8_t kProtocolVersion = 1;

namespace detail {
template <class T>
inline std::uint8_t* put(std::uint8_t* p, T v) {
  std::memcpy(p, &v, sizeof v);  // x86-64 and aarch64 Linux: little-endian, as the wire
  return p + sizeof v;
}
inline std::uint8_t* put3f(std::uint8_t* p, const double* v) {
  for (int d = 0; d < 3; ++d) p = put(p, static_cast<float>(v[d]));
  return p;
}
}  // namespace detail

// One seat's CORNER: `pos`, `vel`, `force` that seat's (3 each), `ball` position then
// velocity (6); the HIP echo of the seat (`hip_seq`, `hip_time`).
inline void encode_corner(std::uint8_t* out, std::int64_t frame, double server_time, int seat,
                          const double* pos, const double* vel, const double* force,
                          double stiffness, const double* ball, std::uint64_t hip_seq,
                          double hip_time) {
  using detail::put;
  using detail::put3f;
  std::uint8_t* p = out;
  p = put(p, kCornerType);
  p = put(p, kProtocolVersion);
  p = put(p, std::uint16_t(0));
  p = put(p, std::uint32_t(std::uint64_t(frame) & 0xFFFFFFFFu));
  p = put(p, server_time);
  p = put(p, frame);
  p = put(p, std::uint8_t(seat));
  const std::uint8_t pad[3] = {0, 0, 0};
  std::memcpy(p, pad, 3);
  p += 3;
  p = put3f(p, pos);
  p = put3f(p, vel);
  p = put3f(p, force);
  p = put(p, static_cast<float>(stiffness));
  p = put3f(p, ball);
  p = put3f(p, ball + 3);
  p = put(p, std::uint32_t(hip_seq & 0xFFFFFFFFu));
  put(p, hip_time);
}

}  // namespace cb::loop
