// The Falcon's 16-byte packet codec (normal mode, lock-step: one host packet, one reply).
//
// A packet is '<', 14 payload bytes, '>'. Each payload byte is 0x41 + a value; numbers are
// signed 16-bit integers written as four nibbles, low nibble first. Because every payload
// byte is >= 0x41, the delimiters '<' (0x3C) and '>' (0x3E) never occur inside a packet,
// which is what lets the reader re-synchronise on them.
#pragma once
#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

namespace clothball_falcon {

constexpr size_t kPacketSize = 16;
constexpr uint8_t kStart = 0x3C;  // '<'
constexpr uint8_t kEnd = 0x3E;    // '>'
constexpr uint8_t kNibbleBase = 0x41;

// Host -> device flags (byte 13).
constexpr uint8_t kFlagHoming = 0x1;
constexpr uint8_t kFlagGreen = 0x2;
constexpr uint8_t kFlagBlue = 0x4;
constexpr uint8_t kFlagRed = 0x8;

// Device -> host buttons (bits 0-3 of byte 13 - 0x41) and homed flags (bits 4-6).
constexpr uint8_t kButtonPlus = 0x1;
constexpr uint8_t kButtonForward = 0x2;
constexpr uint8_t kButtonCentre = 0x4;
constexpr uint8_t kButtonMinus = 0x8;

using Packet = std::array<uint8_t, kPacketSize>;

struct HostCommand {
  std::array<int16_t, 3> motor{0, 0, 0};
  uint8_t flags = 0;  // kFlag*
};

struct DeviceReport {
  std::array<int16_t, 3> encoder{0, 0, 0};
  uint8_t buttons = 0;  // kButton*
  uint8_t homed = 0;    // bit i: encoder i homed
  bool all_homed() const { return (homed & 0x7) == 0x7; }
};

Packet encode_command(const HostCommand& c);
std::optional<HostCommand> decode_command(const Packet& p);  // used by the emulator
Packet encode_report(const DeviceReport& r);                 // used by the emulator
std::optional<DeviceReport> decode_report(const Packet& p);

// Accumulates raw bytes and yields whole, valid packets. Bytes before a '<', packets with a
// misplaced delimiter and packets with out-of-range payload bytes are dropped (counted);
// an incomplete tail is kept for the next feed().
class PacketReader {
 public:
  void feed(const uint8_t* data, size_t n);
  std::optional<Packet> next();
  size_t pending() const { return buf_.size(); }
  size_t dropped_bytes() const { return dropped_; }
  void clear() { buf_.clear(); }

 private:
  std::vector<uint8_t> buf_;
  size_t dropped_ = 0;
};

// FTDI chips prefix every max-packet-size chunk of an IN transfer with 2 status bytes.
// Returns the payload bytes of a raw transfer of `n` bytes.
std::vector<uint8_t> strip_ftdi_status(const uint8_t* raw, size_t n, size_t max_packet = 64);

}  // namespace clothball_falcon
