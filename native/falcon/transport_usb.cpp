// The libusb-1.0 transport. Compiled in only when CMake found libusb
// (CLOTHBALL_HAVE_LIBUSB); otherwise opening it is a clear runtime error.
#include "errors.hpp"
#include "transport.hpp"

#ifdef CLOTHBALL_HAVE_LIBUSB
#include <libusb.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <mutex>
#include <vector>

#include "codec.hpp"
#endif

namespace clothball_falcon {

#ifndef CLOTHBALL_HAVE_LIBUSB

bool usb_transport_available() { return false; }
int count_usb_devices() { return 0; }
std::shared_ptr<Transport> open_usb_transport(int) {
  throw NoDeviceError(
      "this clothball build has no USB Falcon transport (libusb-1.0 was not found when it "
      "was built): install libusb-1.0-0-dev (Debian/Ubuntu) and rebuild, or use the "
      "emulator (--emulator / --device falcon-emulator)");
}

#else

namespace {

std::string usb_error(int rc) { return libusb_error_name(rc); }

class UsbContext {
 public:
  UsbContext() {
    const int rc = libusb_init(&ctx_);
    if (rc != 0) throw NoDeviceError("libusb could not start: " + usb_error(rc));
  }
  ~UsbContext() { libusb_exit(ctx_); }
  UsbContext(const UsbContext&) = delete;
  UsbContext& operator=(const UsbContext&) = delete;
  libusb_context* get() const { return ctx_; }

 private:
  libusb_context* ctx_ = nullptr;
};

// All Falcons (0403:cb48) on the bus, referenced (caller unrefs).
std::vector<libusb_device*> find_falcons(libusb_context* ctx) {
  libusb_device** list = nullptr;
  const ssize_t n = libusb_get_device_list(ctx, &list);
  std::vector<libusb_device*> out;
  for (ssize_t i = 0; i < n; ++i) {
    libusb_device_descriptor desc{};
    if (libusb_get_device_descriptor(list[i], &desc) == 0 && desc.idVendor == kVendorId &&
        desc.idProduct == kProductId)
      out.push_back(libusb_ref_device(list[i]));
  }
  if (list) libusb_free_device_list(list, 1);
  return out;
}

class UsbTransport final : public Transport {
 public:
  explicit UsbTransport(int index) : ctx_(std::make_unique<UsbContext>()) {
    auto devices = find_falcons(ctx_->get());
    if (devices.empty())
      throw NoDeviceError(
          "no Novint Falcon found (USB 0403:cb48): plug it in, switch on its power supply, "
          "and check `lsusb | grep -i 0403:cb48`");
    if (index < 0 || index >= int(devices.size())) {
      for (auto* d : devices) libusb_unref_device(d);
      throw NoDeviceError("Falcon #" + std::to_string(index) + " requested but only " +
                          std::to_string(devices.size()) + " found");
    }
    int rc = libusb_open(devices[size_t(index)], &handle_);
    for (auto* d : devices) libusb_unref_device(d);
    if (rc == LIBUSB_ERROR_ACCESS)
      throw AccessDeniedError(
          std::string("permission denied opening the Falcon (USB 0403:cb48). Add this udev "
                      "rule as /etc/udev/rules.d/99-novint-falcon.rules:\n  ") +
          udev_rule() +
          "\nthen run `sudo udevadm control --reload-rules && sudo udevadm trigger` and "
          "replug the Falcon");
    if (rc != 0) throw NoDeviceError("could not open the Falcon: " + usb_error(rc));
    libusb_set_auto_detach_kernel_driver(handle_, 1);  // the ftdi_sio driver, if bound
    rc = libusb_claim_interface(handle_, 0);
    if (rc == LIBUSB_ERROR_ACCESS)
      throw AccessDeniedError(std::string("permission denied claiming the Falcon's USB "
                                          "interface; udev rule:\n  ") + udev_rule());
    if (rc != 0) {
      libusb_close(handle_);
      handle_ = nullptr;
      throw NoDeviceError("could not claim the Falcon's USB interface (" + usb_error(rc) +
                          "): is another program using it?");
    }
    claimed_ = true;
  }
  ~UsbTransport() override { close(); }

  void close() override {
    std::lock_guard<std::mutex> lock(mu_);
    if (handle_) {
      if (claimed_) libusb_release_interface(handle_, 0);
      libusb_close(handle_);
      handle_ = nullptr;
    }
  }

  void control(uint8_t request, uint16_t value) override {
    std::lock_guard<std::mutex> lock(mu_);
    require_open();
    // The baud request carries the divisor's high bits in wIndex (0 here); the others
    // name the port (1 = interface A).
    uint16_t index = request == ftdi::kBaudRate ? 0 : 1;
    const int rc = libusb_control_transfer(handle_, 0x40, request, value, index, nullptr, 0, 1000);
    check(rc, "control request");
  }

  void write(const uint8_t* data, size_t n) override {
    std::lock_guard<std::mutex> lock(mu_);
    require_open();
    size_t done = 0;
    while (done < n) {
      int sent = 0;
      const int rc = libusb_bulk_transfer(handle_, kEndpointOut, const_cast<uint8_t*>(data + done),
                                          int(n - done), &sent, 1000);
      check(rc, "write");
      if (sent <= 0) throw DeviceGoneError("the Falcon stopped accepting data");
      done += size_t(sent);
    }
  }

  size_t read(uint8_t* out, size_t max, int timeout_ms) override {
    std::lock_guard<std::mutex> lock(mu_);
    require_open();
    // Hand out bytes left over from an earlier transfer first.
    if (!spill_.empty()) return take_spill(out, max);
    const auto deadline =
        std::chrono::steady_clock::now() + std::chrono::milliseconds(std::max(timeout_ms, 0));
    for (;;) {
      uint8_t raw[64];
      int got = 0;
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                            deadline - std::chrono::steady_clock::now()).count();
      const int rc = libusb_bulk_transfer(handle_, kEndpointIn, raw, sizeof raw, &got,
                                          unsigned(std::max<long long>(left, 1)));
      if (rc == LIBUSB_ERROR_TIMEOUT) return 0;
      check(rc, "read");
      // Every 64-byte IN transfer starts with 2 FTDI status bytes.
      auto payload = strip_ftdi_status(raw, size_t(got), 64);
      if (!payload.empty()) {
        spill_.insert(spill_.end(), payload.begin(), payload.end());
        return take_spill(out, max);
      }
      if (std::chrono::steady_clock::now() >= deadline) return 0;
    }
  }

  std::string describe() const override { return "Novint Falcon on USB (libusb)"; }

 private:
  std::unique_ptr<UsbContext> ctx_;
  libusb_device_handle* handle_ = nullptr;
  bool claimed_ = false;
  std::mutex mu_;
  std::vector<uint8_t> spill_;

  size_t take_spill(uint8_t* out, size_t max) {
    const size_t n = std::min(max, spill_.size());
    std::memcpy(out, spill_.data(), n);
    spill_.erase(spill_.begin(), spill_.begin() + long(n));
    return n;
  }
  void require_open() const {
    if (!handle_) throw DeviceGoneError("the Falcon connection is closed");
  }
  static void check(int rc, const char* what) {
    if (rc >= 0) return;
    if (rc == LIBUSB_ERROR_NO_DEVICE || rc == LIBUSB_ERROR_IO || rc == LIBUSB_ERROR_PIPE)
      throw DeviceGoneError(std::string("the Falcon was unplugged or stopped answering (") +
                            what + ": " + usb_error(rc) + ")");
    throw FalconError(std::string("USB ") + what + " failed: " + usb_error(rc));
  }
};

}  // namespace

bool usb_transport_available() { return true; }

int count_usb_devices() {
  UsbContext ctx;
  auto devices = find_falcons(ctx.get());
  for (auto* d : devices) libusb_unref_device(d);
  return int(devices.size());
}

std::shared_ptr<Transport> open_usb_transport(int index) {
  return std::make_shared<UsbTransport>(index);
}

#endif

}  // namespace clothball_falcon
