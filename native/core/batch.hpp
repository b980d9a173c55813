// Many cloths of one configuration (same n, effect set, precision) stepped by one call: the
// engine behind clothball.game.ClothBatch. Each occupied slot is a Backend of its own, so a
// slot runs exactly the code a lone cloth runs (the same core, no second copy of the
// equations). On the CPU the slots are shared among the cores in one parallel region, each
// slot on one thread (no barrier between its substeps); on the GPU a BatchStepper (where
// the backend offers one for the configuration) steps all slots in one graph a frame;
// inputs and outputs cross for all slots at once, one array each way.
#pragma once
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include <omp.h>

#include "backend.hpp"
#include "batch_stepper.hpp"

namespace cb {

class Batch {
 public:
  using Factory = std::function<std::unique_ptr<Backend>(const Config&)>;
  // Asked once, with the first slot's backend, for a stepper of all slots (null: none).
  using StepperFactory = std::function<std::unique_ptr<BatchStepper>(Backend&, int capacity)>;

  // `parallel`: step the slots on `threads` OpenMP threads (CPU backends, each made with
  // one thread; 0: OpenMP's default); else one after another (CUDA backends, which queue
  // their own work, or are stepped together by the stepper `stepper` makes).
  Batch(Factory make, const Config& c, int capacity, bool parallel, int threads = 0,
        StepperFactory stepper = nullptr)
      : make_(std::move(make)),
        make_stepper_(std::move(stepper)),
        cfg_(c),
        slots_(size_t(capacity)),
        active_(size_t(capacity), 1),
        parallel_(parallel),
        threads_(threads) {
    if (capacity < 1) throw std::invalid_argument("capacity must be at least 1");
  }

  int capacity() const { return int(slots_.size()); }
  bool occupied(int s) const { return slots_.at(size_t(s)) != nullptr; }

  // A slot's cloth is made when the slot is opened and freed when it is closed: an idle
  // slot costs no memory. The caller sets its state (Cloth.reset's start).
  void open(int s) {
    if (!slots_.at(size_t(s))) {
      std::unique_ptr<Backend> b = make_(cfg_);
      if (make_stepper_) {
        stepper_ = make_stepper_(*b, capacity());
        make_stepper_ = nullptr;  // the configuration is the batch's: once decides
      }
      if (stepper_) stepper_->attach(s, *b);
      slots_[size_t(s)] = std::move(b);
    }
    active_[size_t(s)] = 1;
  }
  // An inactive slot keeps its state but is not stepped (a room nobody is in sleeps).
  void set_active(int s, bool on) { active_.at(size_t(s)) = on ? 1 : 0; }
  void close(int s) {
    if (stepper_ && slots_.at(size_t(s))) stepper_->detach(s);
    slots_.at(size_t(s)).reset();
  }

  Backend& at(int s) {
    Backend* b = slots_.at(size_t(s)).get();
    if (!b) throw std::out_of_range("slot " + std::to_string(s) + " is free");
    return *b;
  }

  // hips: capacity x 12 (4 corners x 3); rows of free slots are ignored.
  void set_hips_all(const double* h) {
    for (size_t s = 0; s < slots_.size(); ++s)
      if (slots_[s]) slots_[s]->set_hips(h + 12 * s);
  }
  void set_wind_all(const double* w) {  // capacity x 3
    for (size_t s = 0; s < slots_.size(); ++s)
      if (slots_[s]) slots_[s]->set_wind(w + 3 * s);
  }
  // corners: capacity x 24 (4 x position, velocity); balls: capacity x 6. Free slots: 0.
  void get_corners_all(double* corners, double* balls) {
    for (size_t s = 0; s < slots_.size(); ++s) {
      double* c = corners + 24 * s;
      double* b = balls + 6 * s;
      if (slots_[s]) {
        slots_[s]->get_corners(c);
        slots_[s]->get_ball(b);
      } else {
        std::fill(c, c + 24, 0.0);
        std::fill(b, b + 6, 0.0);
      }
    }
  }

  // The node positions of the occupied slots[0..m) into out (m x n*n x 3, row-major
  // nodes): a mesh for each, in one transfer where the stepper offers it (CUDA: one gather
  // copy of all the slots), else one pass over the slots (CPU: a copy each).
  void gather_positions(const int* slots, int m, double* out) {
    if (stepper_ && stepper_->gather_positions(slots, m, out)) return;
    const size_t per = 3 * size_t(cfg_.n) * size_t(cfg_.n);
    for (int k = 0; k < m; ++k) at(slots[k]).get_positions(out + per * size_t(k));
  }

  // Every occupied, active slot advances `frames` frames; finite[s] is 1 for a slot whose
  // state is still finite (and for free or inactive slots), else 0. A slot that fails does
  // not stop the others.
  void step(int frames, int substeps, double dt, std::uint8_t* finite) {
    const int n = capacity();
    std::vector<int> live;
    live.reserve(size_t(n));
    for (int s = 0; s < n; ++s)
      if (slots_[size_t(s)] && active_[size_t(s)]) live.push_back(s);
    const int m = int(live.size());
    if (stepper_) {
      stepper_->step(live.data(), m, frames, substeps, dt);
    } else if (parallel_ && m > 1 && threads_ != 1) {
      const int t = threads_ > 0 ? threads_ : omp_get_max_threads();
#pragma omp parallel for schedule(dynamic, 1) num_threads(t)
      for (int k = 0; k < m; ++k) slots_[size_t(live[size_t(k)])]->step(frames, substeps, dt);
    } else {
      for (int k = 0; k < m; ++k) slots_[size_t(live[size_t(k)])]->step(frames, substeps, dt);
    }
    for (int s = 0; s < n; ++s) finite[s] = !active_[size_t(s)] || slot_finite(s) ? 1 : 0;
  }

 private:
  // As Cloth checks it: every node and the ball finite.
  bool slot_finite(int s) {
    Backend* b = slots_[size_t(s)].get();
    if (!b) return true;
    if (!b->state_finite()) return false;
    double pv[6];
    b->get_ball(pv);
    for (double v : pv)
      if (!std::isfinite(v)) return false;
    return true;
  }

  Factory make_;
  StepperFactory make_stepper_;
  Config cfg_;
  // Before slots_, so that the slots (which hold rows of its arrays) go first.
  std::unique_ptr<BatchStepper> stepper_;
  std::vector<std::unique_ptr<Backend>> slots_;
  std::vector<std::uint8_t> active_;
  bool parallel_;
  int threads_;
};

}  // namespace cb
