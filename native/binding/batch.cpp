// pybind11 declarations of the batch engine (native/core/batch.hpp): arrays in and out for
// every slot at once; stepping releases the GIL. Validation lives in the Python facade
// (clothball.game.sim.batch).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <string>

#include "core/batch.hpp"

namespace py = pybind11;
using Array = py::array_t<double, py::array::c_style | py::array::forcecast>;

namespace {

class BatchEngine {
 public:
  BatchEngine(const std::string& backend, bool dbl, cb::Config c, int capacity) : n_(c.n) {
    if (backend == "cpu") {
      c.threads = 1;  // a slot is one thread's work; the slots share the cores
      batch_ = std::make_unique<cb::Batch>(
          [dbl](const cb::Config& k) { return cb::make_cpu_backend(k, dbl); }, c, capacity,
          true);
    } else if (backend == "cuda") {
      batch_ = std::make_unique<cb::Batch>(
          [dbl](const cb::Config& k) { return cb::make_cuda_backend(k, dbl); }, c, capacity,
          false);
    } else {
      throw py::value_error("backend must be 'cpu' or 'cuda', got '" + backend + "'");
    }
  }
  int capacity() const { return batch_->capacity(); }
  void open(int s) { batch_->open(s); }
  void close(int s) { batch_->close(s); }
  void set_hips_all(Array h) { batch_->set_hips_all(checked(h, 12, "hips").data()); }
  void set_wind_all(Array w) { batch_->set_wind_all(checked(w, 3, "wind").data()); }
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
  // One slot's cloth, as Engine offers it for a lone cloth.
  void set_hips(int s, Array h) { batch_->at(s).set_hips(exact(h, 12, "hips").data()); }
  void set_wind(int s, Array w) { batch_->at(s).set_wind(exact(w, 3, "wind").data()); }
  void set_state(int s, Array p, Array v) {
    const size_t m = 3 * size_t(n_) * n_;
    batch_->at(s).set_state(exact(p, m, "positions").data(), exact(v, m, "velocities").data());
  }
  void set_ball(int s, Array pv) { batch_->at(s).set_ball(exact(pv, 6, "ball").data()); }
  Array ball(int s) {
    Array out(6);
    batch_->at(s).get_ball(out.mutable_data());
    return out;
  }
  Array corners(int s) {
    Array out({4, 6});
    batch_->at(s).get_corners(out.mutable_data());
    return out;
  }
  Array positions(int s) { return mesh([&](double* o) { batch_->at(s).get_positions(o); }); }
  Array velocities(int s) { return mesh([&](double* o) { batch_->at(s).get_velocities(o); }); }
  Array normals(int s) { return mesh([&](double* o) { batch_->at(s).get_normals(o); }); }
  bool ball_contact_on(int s) { return batch_->at(s).ball_contact_on(); }
  unsigned compiled_effects(int s) { return batch_->at(s).compiled_effects(); }

 private:
  template <class F>
  Array mesh(F&& fill) {
    Array out({n_, n_, 3});
    fill(out.mutable_data());
    return out;
  }
  // Arrays for every slot: `per` values a slot.
  Array checked(Array a, size_t per, const char* what) const {
    return exact(a, per * size_t(capacity()), what);
  }
  static Array exact(Array a, size_t size, const char* what) {
    if (size_t(a.size()) != size)
      throw py::value_error(std::string(what) + ": expected " + std::to_string(size) +
                            " values, got " + std::to_string(a.size()));
    return a;
  }
  int n_;
  std::unique_ptr<cb::Batch> batch_;
};

}  // namespace

void bind_batch(py::module_& m) {
  py::class_<BatchEngine>(m, "BatchEngine")
      .def(py::init<const std::string&, bool, cb::Config, int>(), py::arg("backend"),
           py::arg("double_precision"), py::arg("config"), py::arg("capacity"))
      .def("capacity", &BatchEngine::capacity)
      .def("open", &BatchEngine::open)
      .def("close", &BatchEngine::close)
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
