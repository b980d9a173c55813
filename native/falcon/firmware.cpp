#include "firmware.hpp"

#include <algorithm>
#include <chrono>
#include <fstream>
#include <iterator>

#include "codec.hpp"
#include "errors.hpp"

namespace clothball_falcon {
namespace {

using Clock = std::chrono::steady_clock;

// Reads exactly n bytes or returns fewer when the deadline passes.
std::vector<uint8_t> read_exactly(Transport& t, size_t n, int timeout_ms) {
  std::vector<uint8_t> out;
  const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
  uint8_t buf[256];
  while (out.size() < n) {
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
    const size_t got = t.read(buf, std::min(sizeof buf, n - out.size()), int(std::max<long long>(left, 0)));
    out.insert(out.end(), buf, buf + got);
    if (got == 0 && Clock::now() >= deadline) break;
  }
  return out;
}

void purge(Transport& t) {
  t.control(ftdi::kReset, ftdi::kPurgeRx);
  t.control(ftdi::kReset, ftdi::kPurgeTx);
}

}  // namespace

std::vector<uint8_t> read_firmware_file(const std::string& path) {
  if (path.empty())
    throw FirmwareError(
        "the Falcon needs its firmware loaded and no firmware file was given: pass "
        "--firmware FILE (Novint's nVent firmware, about 8.5 KB, from Novint's driver; "
        "clothball does not ship it)");
  std::ifstream f(path, std::ios::binary);
  if (!f)
    throw FirmwareError("firmware file not found or unreadable: " + path +
                        " (point --firmware at your copy of Novint's firmware)");
  std::vector<uint8_t> data((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  if (data.empty()) throw FirmwareError("firmware file is empty: " + path);
  return data;
}

void enter_normal_mode(Transport& t) {
  t.control(ftdi::kLatency, 1);
  t.control(ftdi::kBaudRate, ftdi::kBaudNormal);
  purge(t);
}

bool firmware_loaded(Transport& t, int cycles, int timeout_ms) {
  enter_normal_mode(t);
  PacketReader reader;
  const Packet cmd = encode_command(HostCommand{});
  uint8_t buf[64];
  for (int i = 0; i < cycles; ++i) {
    t.write(cmd.data(), cmd.size());
    const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
    while (Clock::now() < deadline) {
      const size_t got = t.read(buf, sizeof buf, timeout_ms);
      reader.feed(buf, got);
      while (auto p = reader.next())
        if (decode_report(*p)) return true;
      if (got == 0) break;
    }
  }
  return false;
}

void load_firmware_once(Transport& t, const std::vector<uint8_t>& image,
                        const FirmwareOptions& opt) {
  // 1. Purge; latency 16 ms; 9600 baud; 8N1; no flow control.
  purge(t);
  t.control(ftdi::kLatency, 16);
  t.control(ftdi::kBaudRate, ftdi::kBaudFirmware);
  t.control(ftdi::kDataFormat, ftdi::k8N1);
  t.control(ftdi::kFlowCtrl, 0);
  // 2. RTS low, DTR low, DTR high (resets the device into its boot loader).
  t.control(ftdi::kModemCtrl, ftdi::kRtsLow);
  t.control(ftdi::kModemCtrl, ftdi::kDtrLow);
  t.control(ftdi::kModemCtrl, ftdi::kDtrHigh);
  // 3. `0A 43 0D` -> `0A 44 2C 0D`, retried.
  const uint8_t ask[] = {0x0A, 0x43, 0x0D};
  const std::vector<uint8_t> want = {0x0A, 0x44, 0x2C, 0x0D};
  bool answered = false;
  for (int i = 0; i < opt.handshake_tries && !answered; ++i) {
    t.write(ask, sizeof ask);
    answered = read_exactly(t, want.size(), opt.reply_timeout_ms) == want;
  }
  if (!answered)
    throw FirmwareError("the Falcon did not enter firmware mode (no answer to the handshake "
                        "after " + std::to_string(opt.handshake_tries) + " tries)");
  // 4. DTR low; about 140 kbaud.
  t.control(ftdi::kModemCtrl, ftdi::kDtrLow);
  t.control(ftdi::kBaudRate, ftdi::kBaudUpload);
  // 5. 'A' echoed.
  const uint8_t a = 0x41;
  t.write(&a, 1);
  const auto echo = read_exactly(t, 1, opt.echo_timeout_ms);
  if (echo.size() != 1 || echo[0] != a)
    throw FirmwareError("the Falcon did not accept the upload request (no 'A' echo)");
  // 6. 62-byte chunks, each echoed back and compared.
  for (size_t off = 0; off < image.size(); off += kFirmwareChunk) {
    const size_t n = std::min(kFirmwareChunk, image.size() - off);
    t.write(image.data() + off, n);
    const auto back = read_exactly(t, n, opt.echo_timeout_ms);
    if (back.size() != n)
      throw FirmwareError("firmware upload: no echo for the bytes at offset " +
                          std::to_string(off));
    if (!std::equal(back.begin(), back.end(), image.begin() + long(off)))
      throw FirmwareError("the Falcon rejected the firmware (echo mismatch at offset " +
                          std::to_string(off) + ")");
  }
  // 7. Normal mode.
  enter_normal_mode(t);
}

int load_firmware(Transport& t, const std::vector<uint8_t>& image, const FirmwareOptions& opt) {
  std::string last;
  const int attempts = std::max(1, opt.attempts);
  for (int i = 1; i <= attempts; ++i) {
    try {
      load_firmware_once(t, image, opt);
      if (firmware_loaded(t)) return i;
      last = "the firmware was uploaded but the Falcon does not answer in normal mode";
    } catch (const DeviceGoneError&) {
      throw;
    } catch (const FirmwareError& e) {
      last = e.what();
    }
  }
  throw FirmwareLoadError(
      "loading the Falcon firmware failed after " + std::to_string(attempts) +
      " attempts (last: " + last + "). Loading is flaky on real hardware: plug the Falcon "
      "straight into the computer (not a hub), power-cycle it and retry; check that the file "
      "is Novint's firmware");
}

}  // namespace clothball_falcon
