// Websocket frames (RFC 6455 5.2) in C++: the native side's one home for reading and
// writing their headers (clothball.game.wire.wsframe is Python's). Used by the native
// per-message paths (a gateway's pump, the load bench's clients), which see frames as
// bytes on a socket and never go through a websocket library.
#pragma once
#include <cstddef>
#include <cstdint>
#include <cstring>

namespace cb::net {

constexpr std::uint8_t kOpCont = 0x0, kOpText = 0x1, kOpBinary = 0x2, kOpClose = 0x8,
                       kOpPing = 0x9, kOpPong = 0xA;
constexpr std::uint8_t kFin = 0x80;
constexpr std::size_t kMaxHeader = 14;  // 2 + 8 (length) + 4 (mask key)

// A frame's header as read from a buffer.
struct FrameHead {
  std::uint8_t b0 = 0;        // FIN, RSV and opcode
  bool masked = false;
  std::uint64_t length = 0;   // of the payload
  std::size_t size = 0;       // of the header, the mask key included
  std::uint8_t key[4] = {0, 0, 0, 0};
  std::uint8_t opcode() const { return b0 & 0x0F; }
  bool fin() const { return (b0 & kFin) != 0; }
  bool control() const { return (b0 & 0x08) != 0; }
};

// The header at `p` (`n` bytes there): true and `h` filled when it is all there.
inline bool read_head(const std::uint8_t* p, std::size_t n, FrameHead& h) {
  if (n < 2) return false;
  std::size_t size = 2;
  std::uint64_t len = p[1] & 0x7F;
  const bool masked = (p[1] & 0x80) != 0;
  if (len == 126) size += 2;
  else if (len == 127) size += 8;
  const std::size_t key_at = size;
  if (masked) size += 4;
  if (n < size) return false;
  if (len == 126) {
    len = (std::uint64_t(p[2]) << 8) | p[3];
  } else if (len == 127) {
    len = 0;
    for (int i = 0; i < 8; ++i) len = (len << 8) | p[2 + i];
  }
  h.b0 = p[0];
  h.masked = masked;
  h.length = len;
  h.size = size;
  if (masked) std::memcpy(h.key, p + key_at, 4);
  else std::memset(h.key, 0, 4);
  return true;
}

// Writes a final frame's header for `opcode` and `length` payload bytes at `out` (at least
// kMaxHeader bytes); `key`: the mask key to write after it (a client's frame), or null.
// Returns the header's size.
inline std::size_t write_head(std::uint8_t* out, std::uint8_t opcode, std::uint64_t length,
                              const std::uint8_t* key = nullptr) {
  const std::uint8_t m = key != nullptr ? 0x80 : 0;
  std::size_t i = 0;
  out[i++] = std::uint8_t(kFin | opcode);
  if (length < 126) {
    out[i++] = std::uint8_t(m | length);
  } else if (length < 65536) {
    out[i++] = std::uint8_t(m | 126);
    out[i++] = std::uint8_t(length >> 8);
    out[i++] = std::uint8_t(length);
  } else {
    out[i++] = std::uint8_t(m | 127);
    for (int s = 56; s >= 0; s -= 8) out[i++] = std::uint8_t(length >> s);
  }
  if (key != nullptr) {
    std::memcpy(out + i, key, 4);
    i += 4;
  }
  return i;
}

// Applies (or removes: the same) the mask `key` to `n` bytes at `p`, the first of which is
// byte `offset` of the payload.
inline void unmask(std::uint8_t* p, std::size_t n, const std::uint8_t key[4],
                   std::size_t offset = 0) {
  for (std::size_t i = 0; i < n; ++i) p[i] ^= key[(offset + i) & 3];
}

}  // namespace cb::net
