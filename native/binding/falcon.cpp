// Python bindings of the Falcon driver (clothball._native.falcon): declarations and small
// conversions only; the logic lives in codec, kinematics, transport_*, emulator, firmware,
// coupling and driver. Blocking calls release the GIL.
#include "binding/falcon.hpp"

#include <pybind11/stl.h>

#include "falcon/codec.hpp"
#include "falcon/coupling.hpp"
#include "falcon/driver.hpp"
#include "falcon/emulator.hpp"
#include "falcon/errors.hpp"
#include "falcon/firmware.hpp"
#include "falcon/kinematics.hpp"
#include "falcon/transport.hpp"

namespace py = pybind11;

namespace clothball_falcon {
namespace {

using release = py::call_guard<py::gil_scoped_release>;
using M3 = std::array<int16_t, 3>;

Packet to_packet(const py::bytes& b) {
  const std::string s = b;
  if (s.size() != kPacketSize) throw py::value_error("a packet is 16 bytes");
  Packet p;
  std::copy(s.begin(), s.end(), p.begin());
  return p;
}
py::bytes to_bytes(const uint8_t* d, size_t n) { return py::bytes(reinterpret_cast<const char*>(d), n); }

py::dict snapshot_dict(const Snapshot& s) {
  py::dict d;
  d["position"] = s.position; d["velocity"] = s.velocity; d["force"] = s.force;
  d["corner"] = s.corner; d["motor"] = s.motor; d["encoder"] = s.encoder;
  d["buttons"] = int(s.buttons); d["homed"] = int(s.homed); d["gain"] = s.gain;
  d["alpha"] = s.alpha; d["window_energy"] = s.window_energy; d["age"] = s.age;
  d["time"] = s.time; d["ticks"] = s.ticks; d["running"] = s.running;
  d["error"] = s.error.empty() ? py::object(py::none()) : py::object(py::str(s.error));
  return d;
}

py::dict stats_dict(const LoopStats& s) {
  py::dict d;
  d["ticks"] = s.ticks; d["missed_replies"] = s.missed_replies; d["late_ticks"] = s.late_ticks;
  d["elapsed"] = s.elapsed; d["rate"] = s.rate; d["period_mean"] = s.period_mean;
  d["period_p50"] = s.period_p50; d["period_p99"] = s.period_p99;
  d["period_min"] = s.period_min; d["period_max"] = s.period_max;
  d["dropped_bytes"] = s.dropped_bytes;
  return d;
}

py::dict coupling_dict(const CouplingOutput& o) {
  py::dict d;
  d["force"] = o.force; d["corner"] = o.corner; d["gain"] = o.gain; d["age"] = o.age;
  d["alpha"] = o.alpha; d["window_energy"] = o.window_energy; d["clamped"] = o.clamped;
  return d;
}

py::dict emulator_dict(const EmulatorState& s) {
  py::dict d;
  d["position"] = s.position; d["velocity"] = s.velocity; d["motor_force"] = s.motor_force;
  d["motor"] = s.motor; d["encoder"] = s.encoder; d["flags"] = int(s.flags);
  d["buttons"] = int(s.buttons); d["homed"] = int(s.homed);
  d["firmware_loaded"] = s.firmware_loaded; d["unplugged"] = s.unplugged;
  d["packets"] = s.packets; d["handshakes"] = s.handshakes; d["uploads"] = s.uploads;
  d["uploaded_bytes"] = s.uploaded_bytes;
  return d;
}

template <class T>
py::object opt(bool ok, const T& v) { return ok ? py::cast(v) : py::none(); }

}  // namespace

void bind(py::module_& m) {
  auto f = m.def_submodule("falcon", "Novint Falcon driver");

  // Errors.
  static py::exception<FalconError> base(f, "FalconError", PyExc_RuntimeError);
  py::register_exception<NoDeviceError>(f, "NoDeviceError", base.ptr());
  py::register_exception<AccessDeniedError>(f, "AccessDeniedError", base.ptr());
  py::register_exception<FirmwareError>(f, "FirmwareError", base.ptr());
  py::register_exception<FirmwareLoadError>(f, "FirmwareLoadError", base.ptr());
  py::register_exception<HomingTimeoutError>(f, "HomingTimeoutError", base.ptr());
  py::register_exception<DeviceGoneError>(f, "DeviceGoneError", base.ptr());
  f.def("udev_rule", &udev_rule);

  // Constants.
  f.attr("VENDOR_ID") = kVendorId; f.attr("PRODUCT_ID") = kProductId;
  f.attr("PACKET_SIZE") = kPacketSize;
  f.attr("FLAG_HOMING") = kFlagHoming; f.attr("FLAG_GREEN") = kFlagGreen;
  f.attr("FLAG_BLUE") = kFlagBlue; f.attr("FLAG_RED") = kFlagRed;
  f.attr("BUTTON_PLUS") = kButtonPlus; f.attr("BUTTON_FORWARD") = kButtonForward;
  f.attr("BUTTON_CENTRE") = kButtonCentre; f.attr("BUTTON_MINUS") = kButtonMinus;
  f.attr("DEG_PER_COUNT") = kDegPerCount; f.attr("ANGLE_OFFSET_DEG") = kAngleOffsetDeg;
  f.attr("MOTOR_PER_TORQUE") = kMotorPerTorque; f.attr("MAX_TORQUE") = kMaxTorque;
  f.attr("MOTOR_LIMIT") = kMotorLimit; f.attr("FIRMWARE_CHUNK") = kFirmwareChunk;
  f.attr("CUBE_HALF_XY") = kCubeHalfXY; f.attr("CUBE_Z_MIN") = kCubeZMin;
  f.attr("CUBE_Z_MAX") = kCubeZMax;

  // Codec.
  f.def("encode_command", [](const M3& motor, int flags) {
    HostCommand c; c.motor = motor; c.flags = uint8_t(flags);
    const Packet p = encode_command(c);
    return to_bytes(p.data(), p.size());
  }, py::arg("motor"), py::arg("flags") = 0);
  f.def("decode_command", [](const py::bytes& b) -> py::object {
    auto c = decode_command(to_packet(b));
    if (!c) return py::none();
    return py::make_tuple(c->motor, int(c->flags));
  });
  f.def("encode_report", [](const M3& enc, int buttons, int homed) {
    DeviceReport r; r.encoder = enc; r.buttons = uint8_t(buttons); r.homed = uint8_t(homed);
    const Packet p = encode_report(r);
    return to_bytes(p.data(), p.size());
  }, py::arg("encoder"), py::arg("buttons") = 0, py::arg("homed") = 0);
  f.def("decode_report", [](const py::bytes& b) -> py::object {
    auto r = decode_report(to_packet(b));
    if (!r) return py::none();
    return py::make_tuple(r->encoder, int(r->buttons), int(r->homed));
  });
  f.def("strip_ftdi_status", [](const py::bytes& b, size_t max_packet) {
    const std::string s = b;
    auto out = strip_ftdi_status(reinterpret_cast<const uint8_t*>(s.data()), s.size(), max_packet);
    return to_bytes(out.data(), out.size());
  }, py::arg("raw"), py::arg("max_packet") = 64);
  py::class_<PacketReader>(f, "PacketReader")
      .def(py::init<>())
      .def("feed", [](PacketReader& r, const py::bytes& b) {
        const std::string s = b;
        r.feed(reinterpret_cast<const uint8_t*>(s.data()), s.size());
      })
      .def("next", [](PacketReader& r) -> py::object {
        auto p = r.next();
        if (!p) return py::none();
        return to_bytes(p->data(), p->size());
      })
      .def_property_readonly("pending", &PacketReader::pending)
      .def_property_readonly("dropped_bytes", &PacketReader::dropped_bytes);

  // Kinematics.
  f.def("encoder_to_angle", &encoder_to_angle);
  f.def("angle_to_encoder", &angle_to_encoder);
  f.def("torques_to_motors", &torques_to_motors, py::arg("tau"), py::arg("limit") = kMotorLimit);
  f.def("motors_to_torques", &motors_to_torques);
  py::class_<Kinematics>(f, "Kinematics")
      .def(py::init<>())
      .def("inverse", [](const Kinematics& k, const Vec3& p) {
        Vec3 t; return opt(k.inverse(p, t), t);
      })
      .def("forward", [](const Kinematics& k, const Vec3& theta, const Vec3& guess, int max_iter,
                         double tol) -> py::object {
        Vec3 p; int it = 0;
        if (!k.forward(theta, guess, p, max_iter, tol, &it)) return py::none();
        return py::make_tuple(p, it);
      }, py::arg("theta"), py::arg("guess") = Vec3{0, 0, 0.08}, py::arg("max_iter") = 15,
         py::arg("tol") = 1e-10)
      .def("jacobian", [](const Kinematics& k, const Vec3& p) -> py::object {
        Vec3 t; Mat3 J;
        return opt(k.inverse(p, t) && k.jacobian(p, t, J), J);
      })
      .def("jacobian_inverse", [](const Kinematics& k, const Vec3& p) -> py::object {
        Vec3 t; Mat3 J;
        return opt(k.inverse(p, t) && k.jacobian_inverse(p, t, J), J);
      })
      .def("torques", [](const Kinematics& k, const Vec3& p, const Vec3& F) -> py::object {
        Vec3 t, tau;
        return opt(k.inverse(p, t) && k.torques(p, t, F, tau), tau);
      })
      .def("force_from_torques", [](const Kinematics& k, const Vec3& p, const Vec3& tau) -> py::object {
        Vec3 t, F;
        return opt(k.inverse(p, t) && k.force_from_torques(p, t, tau, F), F);
      });

  // Coupling (the haptic law, steppable with a scripted clock).
  py::class_<CouplingConfig>(f, "CouplingConfig")
      .def(py::init<>())
      .def_readwrite("stale_after", &CouplingConfig::stale_after)
      .def_readwrite("fade_out", &CouplingConfig::fade_out)
      .def_readwrite("fade_in", &CouplingConfig::fade_in)
      .def_readwrite("max_extrapolation", &CouplingConfig::max_extrapolation)
      .def_readwrite("max_stiffness", &CouplingConfig::max_stiffness)
      .def_readwrite("max_damping", &CouplingConfig::max_damping)
      .def_readwrite("max_force", &CouplingConfig::max_force)
      .def_readwrite("corner_velocity_cutoff_hz", &CouplingConfig::corner_velocity_cutoff_hz)
      .def_readwrite("passivity", &CouplingConfig::passivity)
      .def_readwrite("passivity_window", &CouplingConfig::passivity_window)
      .def_readwrite("max_passivity_damping", &CouplingConfig::max_passivity_damping);
  py::class_<Coupling>(f, "Coupling")
      .def(py::init<const CouplingConfig&>(), py::arg("config") = CouplingConfig())
      .def("set_corner", [](Coupling& c, const Vec3& pos, const Vec3& vel, const Vec3& K,
                            const Vec3& B, double received_at) {
        CornerSample s; s.position = pos; s.velocity = vel; s.stiffness = K; s.damping = B;
        s.received_at = received_at; s.valid = true; c.set_corner(s);
      }, py::arg("position"), py::arg("velocity"), py::arg("stiffness"), py::arg("damping"),
         py::arg("received_at"))
      .def("clear_corner", &Coupling::clear_corner)
      .def("compute", [](Coupling& c, double now, const Vec3& h, const Vec3& hd, double dt) {
        return coupling_dict(c.compute(now, h, hd, dt));
      }, py::arg("now"), py::arg("h"), py::arg("hdot"), py::arg("dt"))
      .def("reset", &Coupling::reset)
      .def_property_readonly("total_generated", &Coupling::total_generated)
      .def_property_readonly("total_dissipated", &Coupling::total_dissipated);

  // Transports.
  py::class_<Transport, std::shared_ptr<Transport>>(f, "Transport")
      .def("control", &Transport::control, release())
      .def("write", [](Transport& t, const py::bytes& b) {
        const std::string s = b;
        py::gil_scoped_release r;
        t.write(reinterpret_cast<const uint8_t*>(s.data()), s.size());
      })
      .def("read", [](Transport& t, size_t max, int timeout_ms) {
        std::vector<uint8_t> buf(max);
        size_t n;
        { py::gil_scoped_release r; n = t.read(buf.data(), max, timeout_ms); }
        return to_bytes(buf.data(), n);
      }, py::arg("max") = 64, py::arg("timeout_ms") = 10)
      .def("describe", &Transport::describe)
      .def("close", &Transport::close, release());
  f.def("open_usb_transport", &open_usb_transport, py::arg("index") = 0, release());
  f.def("count_usb_devices", &count_usb_devices, release());
  f.def("usb_transport_available", &usb_transport_available);

  py::class_<EmulatorOptions>(f, "EmulatorOptions")
      .def(py::init<>())
      .def_readwrite("firmware_loaded", &EmulatorOptions::firmware_loaded)
      .def_readwrite("handshake_failures", &EmulatorOptions::handshake_failures)
      .def_readwrite("rejected_uploads", &EmulatorOptions::rejected_uploads)
      .def_readwrite("home_after_packets", &EmulatorOptions::home_after_packets)
      .def_readwrite("fragment", &EmulatorOptions::fragment)
      .def_readwrite("step", &EmulatorOptions::step)
      .def_readwrite("hand_mass", &EmulatorOptions::hand_mass)
      .def_readwrite("hand_damping", &EmulatorOptions::hand_damping)
      .def_readwrite("seed", &EmulatorOptions::seed);
  py::class_<EmulatorTransport, Transport, std::shared_ptr<EmulatorTransport>>(f, "EmulatorTransport")
      .def(py::init<const EmulatorOptions&>(), py::arg("options") = EmulatorOptions())
      .def("set_user", &EmulatorTransport::set_user, py::arg("target"), py::arg("stiffness"),
           py::arg("damping") = 0.0)
      .def("set_position", &EmulatorTransport::set_position)
      .def("set_buttons", &EmulatorTransport::set_buttons)
      .def("unplug", &EmulatorTransport::unplug)
      .def("state", [](const EmulatorTransport& e) { return emulator_dict(e.state()); })
      .def("uploaded", [](const EmulatorTransport& e) {
        auto u = e.uploaded(); return to_bytes(u.data(), u.size());
      });

  // Firmware.
  py::class_<FirmwareOptions>(f, "FirmwareOptions")
      .def(py::init<>())
      .def_readwrite("handshake_tries", &FirmwareOptions::handshake_tries)
      .def_readwrite("attempts", &FirmwareOptions::attempts)
      .def_readwrite("reply_timeout_ms", &FirmwareOptions::reply_timeout_ms)
      .def_readwrite("echo_timeout_ms", &FirmwareOptions::echo_timeout_ms);
  f.def("firmware_loaded", [](Transport& t) { return firmware_loaded(t); }, release());
  f.def("load_firmware", [](Transport& t, const py::bytes& image, const FirmwareOptions& o) {
    const std::string s = image;
    std::vector<uint8_t> img(s.begin(), s.end());
    py::gil_scoped_release r;
    return load_firmware(t, img, o);
  }, py::arg("transport"), py::arg("image"), py::arg("options") = FirmwareOptions());

  // Driver.
  py::class_<DriverConfig>(f, "DriverConfig")
      .def(py::init<>())
      .def_readwrite("coupling", &DriverConfig::coupling)
      .def_readwrite("period", &DriverConfig::period)
      .def_readwrite("velocity_cutoff_hz", &DriverConfig::velocity_cutoff_hz)
      .def_readwrite("read_timeout_ms", &DriverConfig::read_timeout_ms)
      .def_readwrite("max_missed_replies", &DriverConfig::max_missed_replies)
      .def_readwrite("realtime", &DriverConfig::realtime);
  py::class_<Driver>(f, "Driver")
      .def(py::init<std::shared_ptr<Transport>, const DriverConfig&>(), py::arg("transport"),
           py::arg("config") = DriverConfig())
      .def("firmware_loaded", &Driver::firmware_loaded, release())
      .def("ensure_firmware", &Driver::ensure_firmware, py::arg("path"),
           py::arg("options") = FirmwareOptions(), release())
      .def("home", &Driver::home, py::arg("timeout"), release())
      .def("start", &Driver::start, release())
      .def("stop", &Driver::stop, release())
      .def_property_readonly("running", &Driver::running)
      .def("set_corner", &Driver::set_corner, py::arg("position"), py::arg("velocity"),
           py::arg("stiffness"), py::arg("damping"), py::arg("age"))
      .def("set_corner_at", &Driver::set_corner_at, py::arg("position"), py::arg("velocity"),
           py::arg("stiffness"), py::arg("damping"), py::arg("received_at"))
      .def("clear_corner", &Driver::clear_corner)
      .def("set_config", &Driver::set_config)
      .def("config", &Driver::config)
      .def("step", [](Driver& d, double now) {
        Snapshot s;
        { py::gil_scoped_release r; s = d.step(now); }
        return snapshot_dict(s);
      })
      .def("set_force_override", &Driver::set_force_override, py::arg("on"),
           py::arg("force") = Vec3{0, 0, 0})
      .def("snapshot", [](const Driver& d) { return snapshot_dict(d.snapshot()); })
      .def("stats", [](const Driver& d) { return stats_dict(d.stats()); })
      .def("reset_stats", &Driver::reset_stats)
      .def("now", &Driver::now)
      .def("describe", &Driver::describe)
      .def("close", &Driver::close, release());
}

}  // namespace clothball_falcon
