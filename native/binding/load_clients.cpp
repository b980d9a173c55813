// pybind11 declarations of the load bench's native client pump (native/bench/
// load_clients.hpp): Python sets each client up and hands its socket over; calls that wait
// (poll, close) release the GIL. The Python side is clothball.server.bench.benchclients.
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <unistd.h>

#include <cmath>
#include <memory>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

#include "bench/load_clients.hpp"
#include "loop/corner_msg.hpp"
#include "loop/mesh_msg.hpp"

namespace py = pybind11;
namespace lb = cb::bench;

namespace {

using HandTuple = std::tuple<double, double, double, double, double>;

std::unique_ptr<lb::LoadClients> make(double hip_rate, const py::bytes& error_prefix) {
  if (!(hip_rate > 0 && hip_rate <= 1000))
    throw py::value_error("hip_rate must be more than 0 and at most 1000 (HIPs a second)");
  return std::make_unique<lb::LoadClients>(hip_rate, std::string(error_prefix));
}

int add(lb::LoadClients& self, int fd, const py::bytes& pending,
        const std::optional<HandTuple>& hand) {
  if (fd < 0) throw py::value_error("fd must be an open socket's descriptor");
  const int mine = dup(fd);  // the pump's own: the caller closes its socket as it likes
  if (mine < 0) throw py::value_error("fd is not an open descriptor");
  lb::Hand h;
  if (hand) std::tie(h.cx, h.cy, h.cz, h.half_y, h.phase) = *hand;
  return self.add(mine, std::string(pending), hand ? &h : nullptr);
}

py::dict snap(lb::LoadClients& self, bool mark) {
  std::vector<lb::ClientCounts> counts;
  lb::Totals totals;
  std::vector<std::pair<std::uint32_t, std::uint64_t>> hist;
  {
    py::gil_scoped_release release;
    self.snap(mark, counts, totals, hist);
  }
  py::list hips, corners, meshes, texts, bytes, errors, frame, closed;
  for (const auto& c : counts) {
    hips.append(c.hips);
    corners.append(c.corners);
    meshes.append(c.meshes);
    texts.append(c.texts);
    bytes.append(c.bytes);
    errors.append(c.errors);
    frame.append(c.frame);
    closed.append(c.closed);
  }
  py::dict h;
  for (const auto& [i, n] : hist) h[py::int_(i)] = n;
  py::dict d;
  d["hips"] = hips;
  d["corners"] = corners;
  d["meshes"] = meshes;
  d["texts"] = texts;
  d["bytes"] = bytes;
  d["errors"] = errors;
  d["frame"] = frame;
  d["closed"] = closed;
  d["echo_unknown"] = totals.echo_unknown;
  d["echo_mismatch"] = totals.echo_mismatch;
  d["behind"] = totals.behind;
  d["last_error"] = py::bytes(totals.last_error);
  d["hist"] = h;
  return d;
}

}  // namespace

void bind_load_clients(py::module_& m) {
  py::class_<lb::LoadClients> c(m, "LoadClients");
  c.def(py::init(&make), py::arg("hip_rate"), py::arg("error_prefix"))
      .def("add", &add, py::arg("fd"), py::arg("pending"), py::arg("hand"),
           "Hands a set-up client's socket over (duplicated) with the bytes already read "
           "past its setup; hand: a player's (centre x, y, z, half height, phase), or None.")
      .def("start", &lb::LoadClients::start)
      .def("poll", &lb::LoadClients::poll, py::arg("now"), py::arg("wait_ms"),
           py::call_guard<py::gil_scoped_release>())
      .def("snap", &snap, py::arg("mark"))
      .def("close", &lb::LoadClients::close, py::call_guard<py::gil_scoped_release>());
  // What the pump writes and reads, for the tests to compare with game.wire.protocol's, and
  // its histogram's bins, which the bench reads quantiles from.
  py::dict k;
  k["hip_type"] = lb::kHipType;
  k["hip_bytes"] = lb::kHipBytes;
  k["corner_type"] = cb::loop::kCornerType;
  k["corner_bytes"] = cb::loop::kCornerBytes;
  k["mesh_type"] = cb::loop::kMeshType;
  k["protocol_version"] = cb::loop::kProtocolVersion;
  k["hist_bin_s"] = lb::kHistBinS;
  k["hist_bins"] = lb::kHistBins;
  k["sent_ring"] = lb::kSentRing;
  k["hold_max"] = lb::kHoldMax;
  k["out_max"] = lb::kOutMax;
  m.attr("LOAD_CLIENTS") = k;
}
