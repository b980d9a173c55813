// The batch engine's binding class (binding/batch.cpp declares it to Python), shared with
// binding/loop.cpp, whose frame loop steps its batch. pybind11 code only.
#pragma once
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <memory>
#include <string>
#include <vector>

#include "binding/arrays.hpp"
#include "core/batch.hpp"

namespace cbind {

namespace py = pybind11;

class BatchEngine {
 public:
  BatchEngine(const std::string& backend, bool dbl, cb::Config c, int capacity, int threads)
      : n_(c.n) {
    const bool cpu = backend == "cpu";
    if (cpu) c.threads = 1;  // a slot is one thread's work; the slots share the cores
    // CPU slots step in one parallel region; CUDA slots in one graph a frame where the
    // configuration allows (cb::make_cuda_batch_stepper), else each its own, in turn.
    cb::Batch::StepperFactory stepper;
    if (!cpu)
      stepper = [dbl](cb::Backend& first, int cap) {
        return cb::make_cuda_batch_stepper(first, cap, dbl);
      };
    batch_ = std::make_unique<cb::Batch>(backend_factory(backend, dbl), c, capacity,
                                         cpu, threads, std::move(stepper));
  }
  int capacity() const { return batch_->capacity(); }
  int n() const { return n_; }
  cb::Batch& batch() { return *batch_; }
  void open(int s) { batch_->open(s); }
  void close(int s) { batch_->close(s); }
  void set_active(int s, bool on) { batch_->set_active(s, on); }
  void set_hips_all(Array h) { batch_->set_hips_all(per_slot(h, 12, "hips").data()); }
  void set_wind_all(Array w) { batch_->set_wind_all(per_slot(w, 3, "wind").data()); }
  py::tuple corners_all() {
    Array c({capacity(), 4, 6});
    Array b({capacity(), 6});
    batch_->get_corners_all(c.mutable_data(), b.mutable_data());
    return py::make_tuple(c, b);
  }
  py::array_t<bool> step(int frames, int substeps, double dt) {
    py::array_t<bool> finite(capacity());
    {
      py::gil_scoped_release release;
      batch_->step(frames, substeps, dt, reinterpret_cast<std::uint8_t*>(finite.mutable_data()));
    }
    return finite;
  }
  // The positions of `slots` (m, n, n, 3): the loop's mesh gather, one transfer.
  Array gather_positions(std::vector<int> slots) {
    for (int s : slots) batch_->at(s);  // each occupied, else out_of_range
    Array out({py::ssize_t(slots.size()), py::ssize_t(n_), py::ssize_t(n_), py::ssize_t(3)});
    batch_->gather_positions(slots.data(), int(slots.size()), out.mutable_data());
    return out;
  }
  // One slot's cloth, as Engine offers a lone cloth.
  void set_hips(int s, Array h) { io(s).set_hips(h); }
  void set_wind(int s, Array w) { io(s).set_wind(w); }
  void set_state(int s, Array p, Array v) { io(s).set_state(p, v); }
  void set_ball(int s, Array pv) { io(s).set_ball(pv); }
  Array ball(int s) { return io(s).ball(); }
  Array corners(int s) { return io(s).corners(); }
  Array positions(int s) { return io(s).positions(); }
  Array velocities(int s) { return io(s).velocities(); }
  Array normals(int s) { return io(s).normals(); }
  bool ball_contact_on(int s) { return batch_->at(s).ball_contact_on(); }
  unsigned compiled_effects(int s) { return batch_->at(s).compiled_effects(); }

 private:
  Arrays io(int s) { return {batch_->at(s), n_}; }
  // Arrays for every slot: `per` values a slot.
  Array per_slot(Array a, size_t per, const char* what) const {
    return sized(a, per * size_t(capacity()), what);
  }
  int n_;
  std::unique_ptr<cb::Batch> batch_;
};


}  // namespace cbind
