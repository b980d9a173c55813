// clothball._native.Pump: the gateway's pump (net/pump.hpp), a thin binding. Each call
// queues its work for the pump's own thread and returns at once.
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cmath>

#include "net/pump.hpp"

namespace py = pybind11;
namespace cn = cb::net;

namespace {

std::array<double, 3> three(const py::sequence& s, const char* what) {
  if (py::len(s) != 3) throw py::value_error(std::string("a lane's ") + what + ": 3 numbers");
  std::array<double, 3> v{};
  for (int d = 0; d < 3; ++d) v[d] = s[d].cast<double>();
  return v;
}

py::tuple event_tuple(const cn::Event& e) {
  switch (e.kind) {
    case cn::Event::kLane:
      return py::make_tuple("lane", e.conn, py::bytes(e.data));
    case cn::Event::kEnded:
      return py::make_tuple("ended", e.conn, e.between,
                            e.data.empty() ? py::object(py::none()) : py::object(py::str(e.data)),
                            e.frame, e.time);
    case cn::Event::kClosed:
      return py::make_tuple("closed", e.conn);
    case cn::Event::kBlock:
      return py::make_tuple("block", e.conn);
    case cn::Event::kArm:
      return py::make_tuple("arm", e.conn != 0);
  }
  return py::make_tuple("unknown", e.conn);
}

}  // namespace

void bind_pump(py::module_& m) {
  py::class_<cn::Pump>(m, "Pump")
      .def(py::init([](double coalesce_s, double slow_drop_s) {
             if (!std::isfinite(coalesce_s) || coalesce_s < 0 || coalesce_s > 0.01)
               throw py::value_error("the pump's coalescing: 0 to 0.01 s");
             if (!std::isfinite(slow_drop_s) || slow_drop_s <= 0)
               throw py::value_error("the pump's slow_drop_s: a finite number of seconds > 0");
             return std::make_unique<cn::Pump>(coalesce_s, slow_drop_s);
           }),
           py::arg("coalesce_s") = cn::kCoalesceS, py::arg("slow_drop_s") = cn::kSlowDropS)
      .def("add", &cn::Pump::add, py::arg("client_fd"), py::arg("engine_fd"),
           py::arg("to_engine"), py::arg("client_eof"))
      .def(
          "open_lane",
          [](cn::Pump& p, std::int64_t conn, const std::string& room, std::int64_t block,
             int slot, int seat, std::uint64_t occupant, const py::sequence& lo,
             const py::sequence& hi, double corner_interval, double binary_rate,
             double binary_burst, std::int64_t board, std::size_t board_slot) {
            cn::LaneSpec s;
            s.room = room;
            s.block = block;
            s.slot = slot;
            s.seat = seat;
            s.occupant = occupant;
            const auto l = three(lo, "lo"), h = three(hi, "hi");
            for (int d = 0; d < 3; ++d) {
              s.lo[d] = l[d];
              s.hi[d] = h[d];
            }
            if (!std::isfinite(corner_interval) || corner_interval < 0 ||
                !std::isfinite(binary_rate) || binary_rate < 0 ||
                !std::isfinite(binary_burst) || binary_burst < 0)
              throw py::value_error("a lane's interval and rates: finite and >= 0");
            s.corner_interval = corner_interval;
            s.binary_rate = binary_rate;
            s.binary_burst = binary_burst;
            s.board = board;
            s.board_slot = board_slot;
            p.open_lane(conn, std::move(s));
          },
          py::arg("conn"), py::arg("room"), py::arg("block"), py::arg("slot"), py::arg("seat"),
          py::arg("occupant"), py::arg("lo"), py::arg("hi"), py::arg("corner_interval"),
          py::arg("binary_rate"), py::arg("binary_burst"), py::arg("board"),
          py::arg("board_slot"))
      .def("close_lane", &cn::Pump::close_lane, py::arg("conn"))
      .def(
          "set_maps",
          [](cn::Pump& p, const std::vector<std::tuple<std::int64_t, bool, int, std::size_t>>& maps) {
            std::vector<cn::Pump::MapIn> in;
            for (const auto& [id, board, fd, bytes] : maps) in.push_back({id, board, fd, bytes});
            try {
              p.set_maps(in);
            } catch (const std::runtime_error& e) {
              throw py::value_error(e.what());
            }
          },
          py::arg("maps"), "(id, board?, memfd, bytes) each; the fds stay the caller's")
      .def(
          "set_local_maps",
          [](cn::Pump& p, const std::vector<std::tuple<std::int64_t, bool, py::buffer>>& maps) {
            std::vector<cn::Pump::MapIn> in;
            for (const auto& [id, board, buf] : maps) {
              const py::buffer_info info = buf.request(true);
              in.push_back({id, board, -1, std::size_t(info.size * info.itemsize), info.ptr});
            }
            try {
              p.set_maps(in);
            } catch (const std::runtime_error& e) {
              throw py::value_error(e.what());
            }
          },
          py::arg("maps"),
          "(id, board?, writable buffer) each, in this process: the pump reads and writes "
          "that memory as it is; the caller keeps it alive until the pump has stopped or "
          "been given maps without it")
      .def("drop_maps", &cn::Pump::drop_maps)
      .def("set_wake", &cn::Pump::set_wake, py::arg("fd"))
      .def("no_wake", &cn::Pump::no_wake)
      .def("finish", &cn::Pump::finish, py::arg("conn"), py::arg("tail"))
      .def("abort", &cn::Pump::abort, py::arg("conn"))
      .def("stop", &cn::Pump::stop)
      .def_property_readonly("event_fd", &cn::Pump::event_fd)
      .def("take_events",
           [](cn::Pump& p) {
             py::list out;
             for (const cn::Event& e : p.take_events()) out.append(event_tuple(e));
             return out;
           })
      .def_property_readonly("messages_in", &cn::Pump::messages_in)
      .def_property_readonly("messages_out", &cn::Pump::messages_out)
      .def_property_readonly("connections", &cn::Pump::connections)
      .def_property_readonly("slow_drops", &cn::Pump::slow_drops,
                             "clients dropped as too slow (behind past slow_drop_s)")
      .def_property_readonly("slow_drop_s", &cn::Pump::slow_drop_s);
}

namespace {
std::string bytes_of(const py::buffer& b) {
  const py::buffer_info info = b.request();
  return std::string(static_cast<const char*>(info.ptr), std::size_t(info.size * info.itemsize));
}
}  // namespace

// The stream followers the pump runs on each connection (net/follow.hpp), for tests that
// hold them to the cases the Python followers were held to.
void bind_follow(py::module_& m) {
  py::class_<cn::ServerFollow>(m, "ServerFollow")
      .def(py::init<>())
      .def(
          "feed",
          [](cn::ServerFollow& f, py::buffer data, py::object on_lane) {
            const std::string in = bytes_of(data);
            std::string out;
            cn::ServerFollow::OnLane cb;
            if (!on_lane.is_none())
              cb = [&on_lane](std::string_view s) { on_lane(py::bytes(s.data(), s.size())); };
            f.feed(reinterpret_cast<const std::uint8_t*>(in.data()), in.size(), out, cb);
            return py::bytes(out);
          },
          py::arg("data"), py::arg("on_lane") = py::none())
      .def("sent_binary",
           [](cn::ServerFollow& f, py::buffer payload) {
             const std::string p = bytes_of(payload);
             f.sent_binary(reinterpret_cast<const std::uint8_t*>(p.data()), p.size());
           })
      .def("between_messages", &cn::ServerFollow::between_messages)
      .def_readonly("websocket", &cn::ServerFollow::websocket)
      .def_readonly("given_up", &cn::ServerFollow::given_up)
      .def_readonly("closed", &cn::ServerFollow::closed)
      .def_property_readonly("room",
                             [](const cn::ServerFollow& f) -> py::object {
                               if (f.room.empty()) return py::none();
                               return py::str(f.room);
                             })
      .def_readonly("frame", &cn::ServerFollow::frame)
      .def_readonly("time", &cn::ServerFollow::time);
  py::class_<cn::ClientTap>(m, "ClientTap")
      .def(py::init<std::size_t>(), py::arg("max_take"))
      .def(
          "feed",
          [](cn::ClientTap& t, py::buffer data, py::function take) {
            const std::string in = bytes_of(data);
            std::string out;
            t.feed(reinterpret_cast<const std::uint8_t*>(in.data()), in.size(), out,
                   [&take](const std::uint8_t* p, std::size_t n) {
                     return take(py::bytes(reinterpret_cast<const char*>(p), n)).cast<bool>();
                   });
            return py::bytes(out);
          },
          py::arg("data"), py::arg("take"));
}
