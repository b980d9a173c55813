// pybind11 declarations of the batch engine (native/core/batch.hpp): arrays in and out for
// every slot at once; stepping releases the GIL. Validation lives in the Python facade
// (clothball.game.sim.batch).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <string>

#include "binding/arrays.hpp"
#include "core/batch.hpp"

namespace py = pybind11;
using cbind::Array;

namespace {

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
    batch_ = std::make_unique<cb::Batch>(cbind::backend_factory(backend, dbl), c, capacity,
                                         cpu, threads, std::move(stepper));
  }
  int capacity() const { return batch_->capacity(); }
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
  cbind::Arrays io(int s) { return {batch_->at(s), n_}; }
  // Arrays for every slot: `per` values a slot.
  Array per_slot(Array a, size_t per, const char* what) const {
    return cbind::sized(a, per * size_t(capacity()), what);
  }
  int n_;
  std::unique_ptr<cb::Batch> batch_;
};

}  // namespace

void bind_batch(py::module_& m) {
  py::class_<BatchEngine>(m, "BatchEngine")
      .def(py::init<const std::string&, bool, cb::Config, int, int>(), py::arg("backend"),
           py::arg("double_precision"), py::arg("config"), py::arg("capacity"),
           py::arg("threads") = 0)
      .def("capacity", &BatchEngine::capacity)
      .def("open", &BatchEngine::open)
      .def("close", &BatchEngine::close)
      .def("set_active", &BatchEngine::set_active, py::arg("slot"), py::arg("active"))
      .def("set_hips_all", &BatchEngine::set_hips_all)
      .def("set_wind_all", &BatchEngine::set_wind_all)
      .def("corners_all", &BatchEngine::corners_all)
      .def("step", &BatchEngine::step, py::arg("frames"), py::arg("substeps"), py::arg("dt"))
      .def("set_hips", &BatchEngine::set_hips)
      .def("set_wind", &BatchEngine::set_wind)
      .def("set_state", &BatchEngine::set_state)
      .def("set_ball", &BatchEngine::set_ball)
      .def("ball", &BatchEngine::ball)
      .def("corners", &BatchEngine::corners)
      .def("positions", &BatchEngine::positions)
      .def("velocities", &BatchEngine::velocities)
      .def("normals", &BatchEngine::normals)
      .def("ball_contact_on", &BatchEngine::ball_contact_on)
      .def("compiled_effects", &BatchEngine::compiled_effects);
}
