// Error types of the Falcon driver. Each maps to a Python exception in binding/falcon.cpp, and
// every message says what the user can do about it.
#pragma once
#include <stdexcept>
#include <string>

namespace clothball_falcon {

struct FalconError : std::runtime_error {
  using std::runtime_error::runtime_error;
};
// No Falcon (USB 0403:cb48) on the bus, or this build cannot reach USB at all.
struct NoDeviceError : FalconError {
  using FalconError::FalconError;
};
// The device exists but the user may not open it (udev rule missing on Linux).
struct AccessDeniedError : FalconError {
  using FalconError::FalconError;
};
// Firmware file missing/unreadable, or the device rejected it (echo mismatch).
struct FirmwareError : FalconError {
  using FalconError::FalconError;
};
// Firmware upload failed on every one of the bounded retries.
struct FirmwareLoadError : FalconError {
  using FalconError::FalconError;
};
// The user did not complete homing in time.
struct HomingTimeoutError : FalconError {
  using FalconError::FalconError;
};
// The device vanished (unplugged) or stopped answering.
struct DeviceGoneError : FalconError {
  using FalconError::FalconError;
};

// The udev rule that grants access to the Falcon; printed with AccessDeniedError.
inline const char* udev_rule() {
  return "SUBSYSTEM==\"usb\", ATTRS{idVendor}==\"0403\", ATTRS{idProduct}==\"cb48\", "
         "MODE=\"0660\", TAG+=\"uaccess\"";
}

}  // namespace clothball_falcon
