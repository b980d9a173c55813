// The byte pipe to a Falcon: a real FTDI chip over libusb, or the emulator. The driver
// speaks only through this interface, so the handshake, upload and 1 kHz loop are tested
// end to end against the emulator.
#pragma once
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

namespace clothball_falcon {

constexpr uint16_t kVendorId = 0x0403;
constexpr uint16_t kProductId = 0xCB48;
constexpr uint8_t kEndpointOut = 0x02;
constexpr uint8_t kEndpointIn = 0x81;

// FTDI vendor requests (bmRequestType 0x40).
namespace ftdi {
constexpr uint8_t kReset = 0;        // value 0 reset, 1 purge RX, 2 purge TX
constexpr uint8_t kModemCtrl = 1;    // value (mask << 8) | state; DTR bit 0, RTS bit 1
constexpr uint8_t kFlowCtrl = 2;     // value 0, index (flow << 8) | port; 0 = no flow control
constexpr uint8_t kBaudRate = 3;     // value = divisor
constexpr uint8_t kDataFormat = 4;   // value 8 = 8N1
constexpr uint8_t kLatency = 9;      // value = milliseconds
constexpr uint16_t kPurgeRx = 1, kPurgeTx = 2;
constexpr uint16_t kDtrHigh = 0x0101, kDtrLow = 0x0100, kRtsHigh = 0x0202, kRtsLow = 0x0200;
constexpr uint16_t k8N1 = 8;
constexpr uint16_t kBaudFirmware = 0x4138;  // 9600 baud
constexpr uint16_t kBaudUpload = 0x15;      // about 140 kbaud
constexpr uint16_t kBaudNormal = 0x2;       // 1.5 Mbaud
}  // namespace ftdi

class Transport {
 public:
  virtual ~Transport() = default;
  // FTDI vendor control request. Throws DeviceGoneError when the device vanished.
  virtual void control(uint8_t request, uint16_t value) = 0;
  // Writes all bytes (or throws).
  virtual void write(const uint8_t* data, size_t n) = 0;
  // Reads up to `max` payload bytes (FTDI status bytes already stripped), waiting at most
  // timeout_ms for the first ones; returns 0 on timeout.
  virtual size_t read(uint8_t* out, size_t max, int timeout_ms) = 0;
  virtual std::string describe() const = 0;
  virtual void close() {}
};

// Opens the index-th Falcon on the USB bus. Throws NoDeviceError, AccessDeniedError (with
// the udev rule), or FalconError (libusb left out of this build).
std::shared_ptr<Transport> open_usb_transport(int index = 0);
// How many Falcons the USB bus shows (0 without libusb).
int count_usb_devices();
bool usb_transport_available();

}  // namespace clothball_falcon
