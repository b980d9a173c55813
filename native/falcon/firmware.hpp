// Firmware mode, firmware upload and normal mode (see docs/falcon.md). The firmware is
// Novint's and is never shipped: the user points us at their own copy.
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include "transport.hpp"

namespace clothball_falcon {

struct FirmwareOptions {
  int handshake_tries = 100;   // `0A 43 0D` -> `0A 44 2C 0D` attempts per load
  int attempts = 10;           // whole-load retries before FirmwareLoadError
  int reply_timeout_ms = 50;   // per handshake reply
  int echo_timeout_ms = 500;   // per 62-byte chunk echo
};

constexpr size_t kFirmwareChunk = 62;

// Reads the firmware file; FirmwareError when it is missing, unreadable or empty.
std::vector<uint8_t> read_firmware_file(const std::string& path);

// Switches the FTDI chip to normal mode: latency 1 ms, 1.5 Mbaud, purge.
void enter_normal_mode(Transport& t);

// Normal mode plus a few I/O cycles: true when any valid reply comes back.
bool firmware_loaded(Transport& t, int cycles = 5, int timeout_ms = 20);

// One load: handshake, upload, normal mode. Throws FirmwareError (rejected echo, no
// handshake answer) or DeviceGoneError.
void load_firmware_once(Transport& t, const std::vector<uint8_t>& image,
                        const FirmwareOptions& opt);

// Up to opt.attempts loads; FirmwareLoadError (with the last reason) when all fail.
// Returns the number of attempts used.
int load_firmware(Transport& t, const std::vector<uint8_t>& image, const FirmwareOptions& opt);

}  // namespace clothball_falcon
