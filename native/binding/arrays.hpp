// What the two engine bindings share (module.cpp: one cloth; batch.cpp: a batch of cloths):
// the backend the caller names, and one backend's state as NumPy arrays, sizes checked,
// meshes (n, n, 3) row-major. Validation of values lives in the Python facade.
#pragma once
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <functional>
#include <memory>
#include <string>

#include "core/backend.hpp"

namespace cbind {

namespace py = pybind11;
using Array = py::array_t<double, py::array::c_style | py::array::forcecast>;
using Factory = std::function<std::unique_ptr<cb::Backend>(const cb::Config&)>;

// "cpu" or "cuda", in float64 (dbl) or float32; anything else is a ValueError.
inline Factory backend_factory(const std::string& backend, bool dbl) {
  if (backend == "cpu") return [dbl](const cb::Config& c) { return cb::make_cpu_backend(c, dbl); };
  if (backend == "cuda")
    return [dbl](const cb::Config& c) { return cb::make_cuda_backend(c, dbl); };
  throw py::value_error("backend must be 'cpu' or 'cuda', got '" + backend + "'");
}

// `a` itself when it holds `size` values, else a ValueError naming `what`.
inline Array sized(Array a, size_t size, const char* what) {
  if (size_t(a.size()) != size)
    throw py::value_error(std::string(what) + ": expected " + std::to_string(size) +
                          " values, got " + std::to_string(a.size()));
  return a;
}

// One backend's state as arrays: the lone engine's, and each slot's of a batch.
class Arrays {
 public:
  Arrays(cb::Backend& b, int n) : b_(b), n_(n) {}
  void set_hips(Array h) { b_.set_hips(sized(h, 12, "hips").data()); }
  void set_wind(Array w) { b_.set_wind(sized(w, 3, "wind").data()); }
  void set_state(Array p, Array v) {
    const size_t m = 3 * size_t(n_) * n_;
    b_.set_state(sized(p, m, "positions").data(), sized(v, m, "velocities").data());
  }
  void set_ball(Array pv) { b_.set_ball(sized(pv, 6, "ball").data()); }
  Array ball() {
    Array out(6);
    b_.get_ball(out.mutable_data());
    return out;
  }
  Array corners() {
    Array out({4, 6});
    b_.get_corners(out.mutable_data());
    return out;
  }
  Array positions() { return mesh([&](double* o) { b_.get_positions(o); }); }
  Array velocities() { return mesh([&](double* o) { b_.get_velocities(o); }); }
  Array normals() { return mesh([&](double* o) { b_.get_normals(o); }); }

 private:
  template <class F>
  Array mesh(F&& fill) {
    Array out({n_, n_, 3});
    fill(out.mutable_data());
    return out;
  }
  cb::Backend& b_;
  int n_;
};

}  // namespace cbind
