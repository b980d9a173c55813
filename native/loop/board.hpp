// A board: fixed-size slots of bytes, each written whole by one writer and read whole by
// readers in other processes (the engine's service thread writes each room's newest MESH
// message; the gateways send it to their clients: docs/architecture.md). A slot: a
// sequence lock (odd while written), the length, a frame number, then the bytes from
// kBoardHead on. Plain memory (a memfd), no pointers.
#pragma once
#include <cstddef>
#include <cstdint>
#include <cstring>

#include "loop/block.hpp"

namespace cb::loop {

constexpr std::size_t kBoardHead = 64;

struct BoardSlot {
  std::uint32_t lock;
  std::uint32_t bytes;
  std::int64_t frame;
};

// Write `n` bytes as `frame` into the slot at `slot` (kBoardHead + n within the slot).
inline void board_write(unsigned char* slot, std::int64_t frame, const void* data,
                        std::uint32_t n) {
  auto* h = reinterpret_cast<BoardSlot*>(slot);
  const std::uint32_t v = load(h->lock);
  store(h->lock, v + 1);
  fence();
  std::memcpy(slot + kBoardHead, data, n);
  h->bytes = n;
  store(h->frame, frame);  // read alone, without the lock, to see whether it is newer
  store(h->lock, v + 2);
}

// The slot's frame (-1: never written), and its bytes copied into `out` (capacity
// `cap`) when that frame is newer than `after`: the length, else 0 (not newer), or -1
// when no consistent copy was had (a writer that died mid-write: the slot is lost).
inline std::int64_t board_read(const unsigned char* slot, std::int64_t after,
                               unsigned char* out, std::size_t cap, std::int64_t& frame) {
  const auto* h = reinterpret_cast<const BoardSlot*>(slot);
  for (int spins = 0; spins < kLockSpins; ++spins) {
    const std::uint32_t v0 = load(h->lock);
    if (v0 & 1u) continue;
    if (v0 == 0) {
      frame = -1;
      return 0;
    }
    frame = load(h->frame);
    if (frame <= after) return 0;
    const std::uint32_t n = h->bytes;
    if (n > cap) return -1;
    std::memcpy(out, slot + kBoardHead, n);
    fence();
    if (load(h->lock) == v0) return std::int64_t(n);
  }
  return -1;
}

}  // namespace cb::loop
