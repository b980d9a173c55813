// A HIP message (docs/protocol.md, "HIP"; clothball.game.wire.protocol.encode_hip): a
// player's hand, little-endian, packed: header <BBHId (type 1, version 1, flags 0, seq,
// client time), then <3f (the position). Read by a gateway's pump (net/pump.cpp) and
// written by the load bench's clients (bench/load_clients.cpp); their tests hold these to
// protocol.py's.
#pragma once
#include <cstddef>
#include <cstdint>

namespace cb::loop {

constexpr std::uint8_t kHipType = 1;
constexpr std::size_t kHipBytes = 28;

}  // namespace cb::loop
