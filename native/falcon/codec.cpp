#include "codec.hpp"

#include <algorithm>

namespace clothball_falcon {
namespace {

void put_int16(uint8_t* out, int16_t v) {
  const auto u = static_cast<uint16_t>(v);
  for (int i = 0; i < 4; ++i) out[i] = uint8_t(kNibbleBase + ((u >> (4 * i)) & 0xF));
}

bool get_nibble(uint8_t b, uint8_t& v) {
  if (b < kNibbleBase || b > kNibbleBase + 0xF) return false;
  v = uint8_t(b - kNibbleBase);
  return true;
}

bool get_int16(const uint8_t* in, int16_t& v) {
  uint16_t u = 0;
  for (int i = 0; i < 4; ++i) {
    uint8_t n;
    if (!get_nibble(in[i], n)) return false;
    u = uint16_t(u | (uint16_t(n) << (4 * i)));
  }
  v = static_cast<int16_t>(u);
  return true;
}

bool framed(const Packet& p) { return p[0] == kStart && p[kPacketSize - 1] == kEnd; }

}  // namespace

Packet encode_command(const HostCommand& c) {
  Packet p{};
  p[0] = kStart;
  for (int m = 0; m < 3; ++m) put_int16(&p[1 + 4 * m], c.motor[m]);
  p[13] = uint8_t(kNibbleBase + (c.flags & 0xF));
  p[14] = kNibbleBase;
  p[15] = kEnd;
  return p;
}

std::optional<HostCommand> decode_command(const Packet& p) {
  if (!framed(p)) return std::nullopt;
  HostCommand c;
  for (int m = 0; m < 3; ++m)
    if (!get_int16(&p[1 + 4 * m], c.motor[m])) return std::nullopt;
  uint8_t flags, zero;
  if (!get_nibble(p[13], flags) || !get_nibble(p[14], zero)) return std::nullopt;
  c.flags = flags;
  return c;
}

Packet encode_report(const DeviceReport& r) {
  Packet p{};
  p[0] = kStart;
  for (int m = 0; m < 3; ++m) put_int16(&p[1 + 4 * m], r.encoder[m]);
  p[13] = uint8_t(kNibbleBase + ((r.buttons & 0xF) | ((r.homed & 0x7) << 4)));
  p[14] = kNibbleBase;
  p[15] = kEnd;
  return p;
}

std::optional<DeviceReport> decode_report(const Packet& p) {
  if (!framed(p)) return std::nullopt;
  DeviceReport r;
  for (int m = 0; m < 3; ++m)
    if (!get_int16(&p[1 + 4 * m], r.encoder[m])) return std::nullopt;
  // Byte 13 carries 7 bits (buttons and homed flags), so it may exceed a nibble.
  if (p[13] < kNibbleBase || p[13] > kNibbleBase + 0x7F) return std::nullopt;
  const uint8_t info = uint8_t(p[13] - kNibbleBase);
  r.buttons = info & 0xF;
  r.homed = (info >> 4) & 0x7;
  return r;
}

void PacketReader::feed(const uint8_t* data, size_t n) { buf_.insert(buf_.end(), data, data + n); }

std::optional<Packet> PacketReader::next() {
  for (;;) {
    // Drop everything before the first '<'.
    auto start = std::find(buf_.begin(), buf_.end(), kStart);
    dropped_ += size_t(start - buf_.begin());
    buf_.erase(buf_.begin(), start);
    if (buf_.empty()) return std::nullopt;
    // Find the first delimiter after the '<'.
    auto delim = std::find_if(buf_.begin() + 1, buf_.end(),
                              [](uint8_t b) { return b == kStart || b == kEnd; });
    if (delim == buf_.end()) {
      if (buf_.size() >= kPacketSize) {  // too long without a delimiter: garbage
        dropped_ += 1;
        buf_.erase(buf_.begin());
        continue;
      }
      return std::nullopt;  // partial tail: keep it
    }
    const size_t at = size_t(delim - buf_.begin());
    if (*delim == kEnd && at == kPacketSize - 1) {
      Packet p;
      std::copy(buf_.begin(), buf_.begin() + kPacketSize, p.begin());
      buf_.erase(buf_.begin(), buf_.begin() + kPacketSize);
      return p;
    }
    // Misplaced delimiter: drop up to it ('>' is dropped too, '<' starts a new packet).
    const size_t drop = *delim == kEnd ? at + 1 : at;
    dropped_ += drop;
    buf_.erase(buf_.begin(), buf_.begin() + drop);
  }
}

std::vector<uint8_t> strip_ftdi_status(const uint8_t* raw, size_t n, size_t max_packet) {
  std::vector<uint8_t> out;
  out.reserve(n);
  for (size_t off = 0; off < n; off += max_packet) {
    const size_t chunk = std::min(max_packet, n - off);
    if (chunk > 2) out.insert(out.end(), raw + off + 2, raw + off + chunk);
  }
  return out;
}

}  // namespace clothball_falcon
