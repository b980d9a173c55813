// pybind11 declarations of the native frame loop (native/loop/): its block's layout, the
// loop over a BatchEngine's batch, and the exit check. Calls that wait (a lock, the
// encoder's wait, stopping) release the GIL. The Python side is clothball.server.frameloop.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <pthread.h>

#include <chrono>
#include <cmath>
#include <cstddef>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "binding/arrays.hpp"
#include "binding/batch_engine.hpp"
#include "loop/block.hpp"
#include "loop/board.hpp"
#include "loop/corner_msg.hpp"
#include "loop/exit.hpp"
#include "loop/frame_loop.hpp"
#include "loop/mesh_msg.hpp"
#include "loop/mesh_quant.hpp"
#include "loop/work_pool.hpp"

namespace py = pybind11;
using cbind::Array;
using cbind::BatchEngine;
namespace lp = cb::loop;

namespace {

// The MESH versions the encoder writes (mesh_msg.hpp): 2, the server's; 1, the old one.
void check_mesh_version(int version) {
  if (version != 1 && version != 2)
    throw py::value_error("version: expected 1 or 2, got " + std::to_string(version));
}

// Version 2's deflater by name: "auto" (the server's: by the cloth's size), "literals" or
// "libdeflate".
lp::MeshDeflater mesh_deflater(const std::string& name) {
  if (name == "auto") return lp::MeshDeflater::kAuto;
  if (name == "literals") return lp::MeshDeflater::kLiterals;
  if (name == "libdeflate") return lp::MeshDeflater::kLibdeflate;
  throw py::value_error("deflater: expected 'auto', 'literals' or 'libdeflate', got '" + name +
                        "'");
}

py::list fields(const lp::Field* f, int count) {
  py::list out;
  for (int k = 0; k < count; ++k) {
    py::tuple shape;
    if (f[k].count > 1)
      shape = f[k].dims[1] == 0 ? py::tuple(py::make_tuple(f[k].dims[0]))
                                : py::tuple(py::make_tuple(f[k].dims[0], f[k].dims[1]));
    out.append(py::make_tuple(f[k].name, f[k].offset, f[k].type, shape));
  }
  return out;
}

// The block's layout, as block.hpp defines it: what Python builds its NumPy views from.
py::dict layout() {
  py::dict d;
  int n = 0;
  d["magic"] = lp::kBlockMagic;
  d["version"] = lp::kBlockVersion;
  d["header_bytes"] = sizeof(lp::Header);
  d["room_bytes"] = sizeof(lp::RoomRecord);
  d["engine_bytes"] = sizeof(lp::EngineRecord);
  d["room_out_bytes"] = offsetof(lp::RoomRecord, events);  // what read_room copies
  d["track_ring"] = lp::kTrackRing;
  d["corner_bytes"] = lp::kCornerBytes;
  d["lateness_ring"] = lp::kLatenessRing;
  const lp::Field* rf = lp::room_fields(&n);
  d["room"] = fields(rf, n);
  const lp::Field* ef = lp::engine_fields(&n);
  d["engine"] = fields(ef, n);
  d["events"] = py::dict(py::arg("corner") = int(lp::kEventCorner),
                         py::arg("exit") = int(lp::kEventExit),
                         py::arg("failed") = int(lp::kEventFailed),
                         py::arg("mesh") = int(lp::kEventMesh));
  return d;
}

// Another process's view of a loop's block (a gateway's: the memfd mapped with mmap): the
// seats' hands in, the CORNER messages out, each under its lock (block.hpp).
class BlockView {
 public:
  explicit BlockView(py::buffer buf)
      : info_(std::make_unique<py::buffer_info>(buf.request(true))) {
    const py::buffer_info& info = *info_;
    if (info.ndim != 1 || info.itemsize != 1)
      throw py::value_error("a frame loop block: expected a writable byte buffer");
    const auto size = std::size_t(info.size);
    if (size < sizeof(lp::Header))
      throw py::value_error("a frame loop block: shorter than its header");
    base_ = static_cast<unsigned char*>(info.ptr);
    const auto* h = reinterpret_cast<const lp::Header*>(base_);
    if (h->magic != lp::kBlockMagic || h->version != lp::kBlockVersion ||
        h->room_bytes != sizeof(lp::RoomRecord) || h->total_bytes > size)
      throw py::value_error("not a frame loop block of this build (magic, version or size)");
    rooms_ = int(h->rooms);
    records_ = reinterpret_cast<lp::RoomRecord*>(base_ + h->rooms_offset);
  }
  int rooms() const { return rooms_; }
  bool write_hip(int slot, int seat, std::uint64_t occupant, double x, double y, double z,
                 std::uint64_t seq, double time) {
    const double p[3] = {x, y, z};
    return lp::write_hand(at(slot, seat), seat, occupant, p, seq, time);
  }
  // (frame, CORNER message, occupant whose hand that frame applied)
  py::tuple read_corner(int slot, int seat) {
    std::uint8_t msg[lp::kCornerBytes];
    std::uint64_t occupant = 0;
    const std::int64_t frame = lp::read_corner(at(slot, seat), seat, msg, occupant);
    return py::make_tuple(frame, py::bytes(reinterpret_cast<const char*>(msg), lp::kCornerBytes),
                          occupant);
  }

 private:
  lp::RoomRecord& at(int slot, int seat) {
    if (slot < 0 || slot >= rooms_) throw py::index_error("slot out of range");
    if (seat < 0 || seat >= lp::kSeats) throw py::index_error("seat out of range");
    return records_[slot];
  }
  // Held while the view lives: the mapping cannot be closed under it (BufferError).
  std::unique_ptr<py::buffer_info> info_;
  unsigned char* base_ = nullptr;
  lp::RoomRecord* records_ = nullptr;
  int rooms_ = 0;
};

// A board's slots (board.hpp) in a writable byte buffer: `offset` is the slot's.
unsigned char* board_slot(const py::buffer_info& info, std::size_t offset, std::size_t n) {
  if (info.ndim != 1 || info.itemsize != 1)
    throw py::value_error("a board: expected a byte buffer");
  if (offset % 64 != 0 || offset + lp::kBoardHead + n > std::size_t(info.size))
    throw py::index_error("a board slot past the board's end (or not 64-byte aligned)");
  return static_cast<unsigned char*>(info.ptr) + offset;
}

class Loop {
 public:
  Loop(BatchEngine& engine, lp::LoopConfig cfg) : engine_(engine) {
    cfg.nodes = engine.n() * engine.n();
    loop_ = std::make_unique<lp::FrameLoop>(engine.batch(), std::move(cfg));
  }
  ~Loop() {
    py::gil_scoped_release release;
    loop_.reset();
  }
  void start() { loop_->start(); }
  // The loop's thread, and the MESH encoders' (take_encoded's): they end with the loop,
  // not when the object is collected (a calibration's pool left three on a 16-core host).
  // A take_encoded after it encodes on its caller alone.
  void stop() {
    py::gil_scoped_release release;
    loop_->stop();
    std::lock_guard<std::mutex> g(pool_mu_);
    pool_.reset();
    stopped_ = true;
  }
  void lock() {
    py::gil_scoped_release release;
    loop_->acquire();
  }
  void unlock() { loop_->release(); }
  void add_room(int slot, bool awake) { loop_->add_room(check(slot), awake); }
  // A room's ball (position then velocity), set between two passes with no Python run
  // while the loop waits: the GIL is let go before the loop's lock is taken and taken back
  // after it is released. (Python holding the lock could wait up to the interpreter's
  // switch interval, 5 ms, for the GIL, and every room of the loop with it.)
  void set_ball(int slot, Array pv) {
    check(slot);
    const Array a = cbind::sized(pv, 6, "ball");
    double v[6];
    std::copy(a.data(), a.data() + 6, v);
    py::gil_scoped_release release;
    loop_->acquire();
    try {
      engine_.batch().at(slot).set_ball(v);
    } catch (...) {
      loop_->release();
      throw;
    }
    loop_->release();
  }
  void remove_room(int slot) { loop_->remove_room(check(slot)); }
  void set_awake(int slot, bool awake) {
    check(slot);
    py::gil_scoped_release release;
    loop_->set_awake(slot, awake);
  }
  void set_hip(int slot, int seat, double x, double y, double z, std::uint64_t seq,
               double time, std::uint64_t occupant) {
    const double p[3] = {x, y, z};
    loop_->set_hip(check(slot), check_seat(seat), p, seq, time, occupant);
  }
  void clear_hip(int slot, int seat, std::uint64_t occupant) {
    loop_->clear_hip(check(slot), check_seat(seat), occupant);
  }
  void set_armed(int slot, bool on) { loop_->set_armed(check(slot), on); }
  void set_recording(int slot, bool on) { loop_->set_recording(check(slot), on); }
  void set_corner_due(int slot, double t) { loop_->set_corner_due(check(slot), t); }
  void set_clock(double t) {
    if (!std::isfinite(t)) throw py::value_error("set_clock: the time must be finite");
    py::gil_scoped_release release;
    loop_->set_clock(t);
  }
  int event_fd() const { return loop_->event_fd(); }
  void add_wake(int fd) { loop_->add_wake(fd); }
  void remove_wake(int fd) {
    py::gil_scoped_release release;  // waits for a pass's writes
    loop_->remove_wake(fd);
  }
  py::tuple take_events() {
    loop_->take_events(slots_, bits_);
    py::array_t<int> s(py::ssize_t(slots_.size()), slots_.data());
    py::array_t<std::uint32_t> b(py::ssize_t(bits_.size()), bits_.data());
    return py::make_tuple(s, b);
  }
  py::bytes read_room(int slot) {
    lp::RoomRecord& r = scratch_;
    loop_->read_room(check(slot), r);
    return py::bytes(reinterpret_cast<const char*>(&r), offsetof(lp::RoomRecord, events));
  }
  bool wait_service(double timeout) {
    py::gil_scoped_release release;
    return loop_->wait_service(timeout);
  }
  void notify_service() { loop_->notify_service(); }
  // The due rooms' meshes (FrameLoop::take_meshes), each encoded as a whole MESH message
  // (loop/mesh_msg.hpp) and written into `board` (a writable buffer of slots of `slot_bytes`, or None), without the GIL, on
  // `threads` threads (this one and threads - 1 kept for the next calls): a list of
  // (slot, frame, message).
  py::list take_encoded(py::object board, std::size_t slot_bytes, double radius,
                        bool compress, int threads) {
    if (threads < 1 || threads > 64)
      throw py::value_error("threads: expected 1..64, got " + std::to_string(threads));
    const int n = engine_.n();
    std::unique_ptr<py::buffer_info> info;
    if (!board.is_none()) {
      info = std::make_unique<py::buffer_info>(py::reinterpret_borrow<py::buffer>(board).request(true));
      if (info->ndim != 1 || info->itemsize != 1)
        throw py::value_error("a board: expected a byte buffer");
      if (slot_bytes % 64 != 0 || slot_bytes < lp::kBoardHead + lp::mesh_msg_max(n) ||
          std::size_t(info->size) < slot_bytes * std::size_t(loop_->capacity()))
        throw py::value_error("a board: its slots cannot hold this loop's meshes");
    }
    std::vector<lp::MeshSnapshot> got;
    std::vector<std::vector<std::uint8_t>> msgs;
    {
      py::gil_scoped_release release;
      got = loop_->take_meshes();
      msgs.resize(got.size());
      std::lock_guard<std::mutex> g(pool_mu_);
      const int use = stopped_ ? 1 : threads;
      if (!pool_ || pool_->threads() != use) {
        pool_.reset();
        pool_ = std::make_unique<lp::WorkPool>(use);
        mesh_scratch_.resize(std::size_t(use));
      }
      // Each message into its own slot of the board: no two items write the same bytes.
      pool_->run(int(got.size()), [&](int i, int t) {
        const lp::MeshSnapshot& m = got[std::size_t(i)];
        std::vector<std::uint8_t>& msg = msgs[std::size_t(i)];
        lp::encode_mesh_msg(msg, mesh_scratch_[std::size_t(t)], m.positions.data(), n, m.frame,
                            m.server_time, m.ball, radius, m.hips, compress);
        if (info)
          lp::board_write(static_cast<unsigned char*>(info->ptr) + std::size_t(m.slot) * slot_bytes,
                          m.frame, msg.data(), std::uint32_t(msg.size()));
      });
    }
    py::list out;
    for (std::size_t i = 0; i < got.size(); ++i)
      out.append(py::make_tuple(got[i].slot, got[i].frame,
                                py::bytes(reinterpret_cast<const char*>(msgs[i].data()),
                                          msgs[i].size())));
    return out;
  }
  py::memoryview block() {
    return py::memoryview::from_memory(loop_->block(), py::ssize_t(loop_->block_size()));
  }
  int block_fd() const { return loop_->block_fd(); }
  double cpu_seconds() const { return loop_->cpu_seconds(); }

 private:
  int check(int slot) const {
    if (slot < 0 || slot >= loop_->capacity())
      throw py::value_error("slot " + std::to_string(slot) + " is not in 0.." +
                            std::to_string(loop_->capacity() - 1));
    return slot;
  }
  static int check_seat(int seat) {
    if (seat < 0 || seat >= lp::kSeats) throw py::value_error("seat must be 0..3");
    return seat;
  }
  BatchEngine& engine_;
  std::unique_ptr<lp::FrameLoop> loop_;
  std::vector<int> slots_;
  std::vector<std::uint32_t> bits_;
  lp::RoomRecord scratch_{};
  std::mutex pool_mu_;                  // pool_ and stopped_: take_encoded against stop
  std::unique_ptr<lp::WorkPool> pool_;  // take_encoded's threads, kept between calls
  bool stopped_ = false;
  std::vector<lp::MeshScratch> mesh_scratch_;  // one a thread
};

std::vector<double> values(Array a, size_t size, const char* what) {
  cbind::sized(a, size, what);
  return {a.data(), a.data() + size};
}

}  // namespace

void bind_loop(py::module_& m) {
  py::class_<lp::LoopConfig>(m, "FrameLoopConfig")
      .def(py::init<>())
      .def_readwrite("frame_dt", &lp::LoopConfig::frame_dt)
      .def_readwrite("epoch", &lp::LoopConfig::epoch)
      .def_readwrite("timer_slack", &lp::LoopConfig::timer_slack)
      .def_readwrite("max_catchup", &lp::LoopConfig::max_catchup)
      .def_readwrite("fixed_substeps", &lp::LoopConfig::fixed_substeps)
      .def_readwrite("substep_speeds", &lp::LoopConfig::substep_speeds)
      .def_readwrite("max_frames_per_call", &lp::LoopConfig::max_frames_per_call)
      .def_readwrite("has_ball", &lp::LoopConfig::has_ball)
      .def_readwrite("floor_y", &lp::LoopConfig::floor_y)
      .def_readwrite("lost_ball_y", &lp::LoopConfig::lost_ball_y)
      .def_readwrite("stiffness", &lp::LoopConfig::stiffness)
      .def_readwrite("mesh_every", &lp::LoopConfig::mesh_every)
      .def_readwrite("track_every", &lp::LoopConfig::track_every)
      .def_readwrite("gust_amplitude", &lp::LoopConfig::gust_amplitude)
      .def_readwrite("gust_period", &lp::LoopConfig::gust_period)
      .def_readwrite("manual_clock", &lp::LoopConfig::manual_clock)
      .def_property(
          "wind", [](const lp::LoopConfig& c) { return std::vector<double>(c.wind, c.wind + 3); },
          [](lp::LoopConfig& c, Array a) {
            auto v = values(a, 3, "wind");
            std::copy(v.begin(), v.end(), c.wind);
          })
      .def_property(
          "ball_start", [](const lp::LoopConfig& c) { return std::vector<double>(c.ball_start, c.ball_start + 3); },
          [](lp::LoopConfig& c, Array a) {
            auto v = values(a, 3, "ball_start");
            std::copy(v.begin(), v.end(), c.ball_start);
          })
      .def_property(
          "anchors", [](const lp::LoopConfig& c) { return std::vector<double>(c.anchors, c.anchors + 12); },
          [](lp::LoopConfig& c, Array a) {
            auto v = values(a, 12, "anchors");
            std::copy(v.begin(), v.end(), c.anchors);
          });
  py::class_<Loop>(m, "FrameLoop")
      .def(py::init<BatchEngine&, lp::LoopConfig>(), py::arg("engine"), py::arg("config"),
           py::keep_alive<1, 2>())
      .def("start", &Loop::start)
      .def("stop", &Loop::stop)
      .def("lock", &Loop::lock)
      .def("unlock", &Loop::unlock)
      .def("add_room", &Loop::add_room, py::arg("slot"), py::arg("awake"))
      .def("set_ball", &Loop::set_ball, py::arg("slot"), py::arg("ball"))
      .def("remove_room", &Loop::remove_room)
      .def("set_awake", &Loop::set_awake)
      .def("set_hip", &Loop::set_hip, py::arg("slot"), py::arg("seat"), py::arg("x"),
           py::arg("y"), py::arg("z"), py::arg("seq"), py::arg("time"), py::arg("occupant"))
      .def("clear_hip", &Loop::clear_hip)
      .def("set_armed", &Loop::set_armed)
      .def("set_recording", &Loop::set_recording)
      .def("set_corner_due", &Loop::set_corner_due)
      .def("set_clock", &Loop::set_clock, py::arg("t"))
      .def("event_fd", &Loop::event_fd)
      .def("add_wake", &Loop::add_wake, py::arg("fd"))
      .def("remove_wake", &Loop::remove_wake, py::arg("fd"))
      .def("take_events", &Loop::take_events)
      .def("read_room", &Loop::read_room)
      .def("wait_service", &Loop::wait_service, py::arg("timeout"))
      .def("notify_service", &Loop::notify_service)
      .def("take_encoded", &Loop::take_encoded, py::arg("board"), py::arg("slot_bytes"),
           py::arg("radius"), py::arg("compress"), py::arg("threads") = 1)
      .def("block", &Loop::block)
      .def("block_fd", &Loop::block_fd)
      .def("cpu_seconds", &Loop::cpu_seconds);
  m.def("frame_block_layout", &layout);
  m.def("board_read", [](py::buffer board, std::size_t offset, std::size_t slot_bytes,
                         std::int64_t after) -> py::tuple {
    const py::buffer_info info = board.request(true);
    const unsigned char* slot = board_slot(info, offset, slot_bytes - lp::kBoardHead);
    // Nothing newer (most looks): answered without a copy.
    const std::int64_t newest = lp::load(reinterpret_cast<const lp::BoardSlot*>(slot)->frame);
    if (newest <= after) return py::make_tuple(newest, py::none());
    std::string out(slot_bytes - lp::kBoardHead, '\0');
    std::int64_t frame = -1;
    const std::int64_t n = lp::board_read(slot, after, reinterpret_cast<unsigned char*>(out.data()),
                                          out.size(), frame);
    if (n <= 0) return py::make_tuple(frame, py::none());
    out.resize(std::size_t(n));
    return py::make_tuple(frame, py::bytes(out));
  }, py::arg("board"), py::arg("offset"), py::arg("slot_bytes"), py::arg("after"));
  py::class_<BlockView>(m, "BlockView")
      .def(py::init<py::buffer>(), py::arg("block"))
      .def_property_readonly("rooms", &BlockView::rooms)
      .def("write_hip", &BlockView::write_hip, py::arg("slot"), py::arg("seat"),
           py::arg("occupant"), py::arg("x"), py::arg("y"), py::arg("z"), py::arg("seq"),
           py::arg("time"))
      .def("read_corner", &BlockView::read_corner, py::arg("slot"), py::arg("seat"));
  // A MESH's quantised nodes and their row deltas (mesh_quant.hpp), off the GIL: what
  // game.wire.protocol.quantise and encode_mesh compute, for the test against them.
  m.def(
      "quantise_mesh",
      [](py::array_t<double, py::array::c_style | py::array::forcecast> positions) {
        if (positions.ndim() != 3 || positions.shape(0) != positions.shape(1) ||
            positions.shape(2) != 3 || positions.shape(0) < 1)
          throw py::value_error("positions: expected (n, n, 3)");
        const py::ssize_t n = positions.shape(0);
        py::array_t<std::uint16_t> q({n, n, py::ssize_t(3)}), delta({n, n, py::ssize_t(3)});
        py::array_t<double> lo(3), hi(3);
        const double* p = positions.data();
        std::uint16_t *qd = q.mutable_data(), *dd = delta.mutable_data();
        double *l = lo.mutable_data(), *h = hi.mutable_data();
        {
          py::gil_scoped_release release;
          lp::quantise_mesh(p, int(n), qd, dd, l, h);
        }
        return py::make_tuple(q, delta, lo, hi);
      },
      py::arg("positions"));
  // The loop's MESH encoder (mesh_msg.hpp), for the test against the Python one.
  m.def(
      "encode_mesh_msg",
      [](py::array_t<double, py::array::c_style | py::array::forcecast> positions,
         std::int64_t frame, double server_time, Array ball, double radius, Array hips,
         bool compress, int version, const std::string& deflater) {
        if (positions.ndim() != 3 || positions.shape(0) != positions.shape(1) ||
            positions.shape(2) != 3 || positions.shape(0) < 1 || positions.shape(0) > 65535)
          throw py::value_error("positions: expected (n, n, 3)");
        check_mesh_version(version);
        const lp::MeshDeflater d = mesh_deflater(deflater);
        cbind::sized(ball, 3, "ball");
        cbind::sized(hips, 12, "hips");
        std::vector<std::uint8_t> out;
        lp::MeshScratch scratch;
        lp::encode_mesh_msg(out, scratch, positions.data(), int(positions.shape(0)), frame,
                            server_time, ball.data(), radius, hips.data(), compress, version,
                            d);
        return py::bytes(reinterpret_cast<const char*>(out.data()), out.size());
      },
      py::arg("positions"), py::arg("frame"), py::arg("server_time"), py::arg("ball"),
      py::arg("radius"), py::arg("hips"), py::arg("compress"),
      py::arg("version") = int(lp::kMeshVersion), py::arg("deflater") = "auto");
  // MESH version 2's deflater alone (huffman_deflate.hpp), for the tests against zlib's
  // inflater on inputs of every shape; None where the stream would pass `cap` bytes.
  m.def(
      "deflate_literals",
      [](py::bytes data, int segments, std::size_t cap) -> py::object {
        if (segments < 1 || segments > 64)
          throw py::value_error("segments: expected 1..64, got " + std::to_string(segments));
        const std::string in = data;
        std::vector<std::uint8_t> out(cap);
        const std::size_t n = lp::huff::zlib_literals(
            reinterpret_cast<const std::uint8_t*>(in.data()), in.size(), segments, out.data(),
            cap);
        if (n == 0) return py::none();
        return py::bytes(reinterpret_cast<const char*>(out.data()), n);
      },
      py::arg("data"), py::arg("segments"), py::arg("cap"));
  // The MESH encoder timed alone, as the service thread runs it (one thread, its scratch
  // kept): each of `states` (k, n, n, 3) encoded in turn, `rounds` times; the seconds of
  // each encode (rounds * k, timed in C++: no binding in them) and each state's bytes.
  m.def(
      "time_mesh_encoder",
      [](py::array_t<double, py::array::c_style | py::array::forcecast> states, int version,
         int rounds, const std::string& deflater) {
        if (states.ndim() != 4 || states.shape(1) != states.shape(2) || states.shape(3) != 3 ||
            states.shape(0) < 1 || states.shape(1) < 1 || states.shape(1) > 65535)
          throw py::value_error("states: expected (k, n, n, 3)");
        check_mesh_version(version);
        const lp::MeshDeflater d = mesh_deflater(deflater);
        if (rounds < 1) throw py::value_error("rounds: expected >= 1");
        const py::ssize_t k = states.shape(0), n = states.shape(1);
        py::array_t<double> seconds(py::ssize_t(rounds) * k);
        py::array_t<std::int64_t> sizes(k);
        double* sec = seconds.mutable_data();
        std::int64_t* sz = sizes.mutable_data();
        const double* p = states.data();
        {
          py::gil_scoped_release release;
          const double zeros[12] = {};
          std::vector<std::uint8_t> out;
          lp::MeshScratch scratch;
          for (int r = 0; r < rounds; ++r)
            for (py::ssize_t i = 0; i < k; ++i) {
              const auto t0 = std::chrono::steady_clock::now();
              lp::encode_mesh_msg(out, scratch, p + std::size_t(i) * std::size_t(n * n * 3),
                                  int(n), i, 0.0, zeros, 0.1, zeros, true, version, d);
              sec[std::size_t(r) * std::size_t(k) + std::size_t(i)] =
                  std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
              sz[i] = std::int64_t(out.size());
            }
        }
        return py::make_tuple(seconds, sizes);
      },
      py::arg("states"), py::arg("version") = int(lp::kMeshVersion), py::arg("rounds") = 50,
      py::arg("deflater") = "auto");
  // The loop's CORNER encoder (corner_msg.hpp), for the test against the Python one.
  m.def("encode_corners",
        [](std::int64_t frame, double server_time, Array pos, Array vel, Array force,
           double stiffness, Array ball, std::vector<std::uint64_t> seq,
           std::vector<double> time) {
          cbind::sized(pos, 12, "positions");
          cbind::sized(vel, 12, "velocities");
          cbind::sized(force, 12, "forces");
          cbind::sized(ball, 6, "ball");
          if (seq.size() != lp::kSeats || time.size() != lp::kSeats)
            throw py::value_error("applied: expected 4 (seq, time) pairs");
          py::list out;
          std::uint8_t msg[lp::kCornerBytes];
          for (int s = 0; s < lp::kSeats; ++s) {
            lp::encode_corner(msg, frame, server_time, s, pos.data() + 3 * s,
                              vel.data() + 3 * s, force.data() + 3 * s, stiffness,
                              ball.data(), seq[s], time[s]);
            out.append(py::bytes(reinterpret_cast<const char*>(msg), lp::kCornerBytes));
          }
          return out;
        });
  m.def("monotonic_now", &lp::monotonic_now);
  // The calling thread's name as the OS knows it (/proc, top), cut to its 15 bytes.
  m.def("name_os_thread", [](const std::string& name) {
    pthread_setname_np(pthread_self(), name.substr(0, 15).c_str());
  });
  m.def("exit_edge", [](Array ball, Array corners, double floor_y) {
    return lp::exit_edge(cbind::sized(ball, 3, "ball").data(),
                         cbind::sized(corners, 12, "corners").data(), floor_y);
  }, py::arg("ball"), py::arg("corners"), py::arg("floor_y"));
}
