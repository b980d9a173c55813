// The native frame loop: one thread per engine (a cb::Batch) that keeps simulated time
// locked to the monotonic clock in 1 ms frames, with every input and output in one memory
// block (block.hpp) and no Python on its path. Each pass it reads every room's newest hands
// (sequence-locked per seat), steps every awake room in one batched call (catching up at
// most max_catchup frames, a quarter of the backlog a pass; older time is dropped and
// counted), publishes every room's corners, forces, ball and frame, checks each armed
// room's ball against its edges (exit.hpp) and every room's state for non-finite values,
// copies the positions of the rooms due for a mesh in one transfer, keeps TRACK samples of
// the rooms being recorded, and appends its lateness to the engine's ring. It tells the
// event loop through an eventfd (one write per batch of events), and the mesh encoder
// through a condition variable. docs/frameloop.md.
#pragma once
#include <condition_variable>
#include <atomic>
#include <cstdint>
#include <limits>
#include <mutex>
#include <thread>
#include <vector>

#include "core/batch.hpp"
#include "loop/block.hpp"

namespace cb::loop {

struct LoopConfig {
  double frame_dt = 1e-3;
  double epoch = 0.0;        // CLOCK_MONOTONIC seconds of server time 0
  double timer_slack = 50e-6;  // a sleep ends up to this late: a frame may start this early
  int max_catchup = 50;
  int fixed_substeps = 0;    // 0: automatic, from substep_speeds and the ball's speed
  // Automatic substeps: [k - 1] is the fastest ball speed k substeps hold (ascending; the
  // scene's stability rule, tabulated by clothball.game.sim.stability).
  std::vector<double> substep_speeds;
  int max_frames_per_call = 10;  // with automatic substeps (re-checked between calls)
  bool has_ball = false;
  double floor_y = 0.0;
  double lost_ball_y = 0.0;      // an unarmed ball below this is put back at ball_start
  double ball_start[3] = {0, 0, 0};
  double stiffness = 0.0;
  double anchors[12] = {};       // each seat's corner at rest (its hand without a HIP)
  int mesh_every = 33;           // frames between meshes (0: none)
  int track_every = 10;          // frames between TRACK samples while recording
  int nodes = 0;                 // n * n
  // Wind gusts (clothball.game.sim.cloth.wind_at): before each frame a room's wind is
  // wind * (1 + gust_amplitude sin(2 pi t / gust_period)), t its simulated time; 0: the
  // wind the batch holds stays.
  double wind[3] = {0, 0, 0};
  double gust_amplitude = 0.0;
  double gust_period = 1.0;
  // The loop's clock is set by set_clock (a test's clock, in seconds of server time from
  // epoch 0) instead of CLOCK_MONOTONIC; the loop waits for it to move instead of sleeping.
  bool manual_clock = false;
};

// A room's mesh snapshot, as the encoder thread takes it.
struct MeshSnapshot {
  int slot = -1;
  std::int64_t frame = 0;
  double server_time = 0.0;
  double ball[6] = {};
  double hips[12] = {};
  std::vector<double> positions;  // nodes x 3
};

double monotonic_now();  // CLOCK_MONOTONIC, s (what Python's time.perf_counter reads)

class FrameLoop {
 public:
  FrameLoop(Batch& batch, LoopConfig cfg);
  ~FrameLoop();
  FrameLoop(const FrameLoop&) = delete;
  FrameLoop& operator=(const FrameLoop&) = delete;

  void start();
  void stop();
  bool running() const;
  // CPU seconds the loop's thread has used (0 before start): what admission control's
  // calibration reads (server/headroom.py), unaffected by time other threads take.
  double cpu_seconds() const;

  // Held by the loop for a whole pass: hold it to change the batch (add, remove, set_ball).
  // Taken with acquire() (no raw mutex is handed out): a loop that is behind runs pass after
  // pass without sleeping, and only a waiter it knows of is let in between two passes.
  void acquire();
  void release() { mutex_.unlock(); }

  // Under acquire(): a room on `slot` (the batch slot is open), frame 0, nothing armed.
  void add_room(int slot, bool awake);
  void remove_room(int slot);
  // Any thread, no lock: the block's inputs.
  void set_awake(int slot, bool awake);
  void set_hip(int slot, int seat, const double* pos, std::uint64_t seq, double time,
               std::uint64_t occupant);
  void clear_hip(int slot, int seat, std::uint64_t occupant);
  void set_armed(int slot, bool armed);
  void set_recording(int slot, bool on);
  void set_corner_due(int slot, double server_time);
  // Any thread: the time a loop with a manual clock (LoopConfig::manual_clock) reads.
  void set_clock(double t);
  // Any thread: eventfds written once a pass, after the pass's corners are published (a
  // gateway's: it sends CORNERs at frame rate from the block, which timers that wait whole
  // milliseconds cannot). The loop does not own them: remove one before closing it.
  void add_wake(int fd);
  void remove_wake(int fd);

  // The event loop's side: the fd it waits on, and the rooms with events (cleared here).
  int event_fd() const { return efd_; }
  int take_events(std::vector<int>& slots, std::vector<std::uint32_t>& bits);
  // A consistent copy of a room's record (the loop's outputs as of one pass).
  void read_room(int slot, RoomRecord& out) const;

  // The encoder thread's side: wait (up to timeout s) for meshes or a notify, then take them.
  bool wait_service(double timeout);
  void notify_service();
  std::vector<MeshSnapshot> take_meshes();

  Header* header() { return hdr_; }
  RoomRecord& room(int slot) { return rooms_[slot]; }
  EngineRecord& engine() { return *eng_; }
  void* block() { return base_; }
  std::size_t block_size() const { return bytes_; }
  int block_fd() const { return memfd_; }
  int capacity() const { return cap_; }

 private:
  void run();
  double now() const;  // the loop's clock: CLOCK_MONOTONIC, or set_clock's
  void set_gusts(const std::vector<int>& live, int frames_into_pass);
  int substeps_for(const std::vector<int>& live);
  void publish(int slot, int frames, double server_time, const double* corners,
               const double* ball, const double* hips, bool& signal);
  void signal();

  Batch& batch_;
  LoopConfig cfg_;
  int cap_;
  // the block
  void* base_ = nullptr;
  std::size_t bytes_ = 0;
  int memfd_ = -1;
  Header* hdr_ = nullptr;
  RoomRecord* rooms_ = nullptr;
  EngineRecord* eng_ = nullptr;
  int efd_ = -1;
  std::uint32_t signalled_ = 0;  // an eventfd write is pending (atomic)
  std::mutex wake_mutex_;
  std::vector<int> wakes_;  // add_wake's
  // the loop's own
  std::mutex mutex_;
  std::atomic<int> waiting_{0};
  std::atomic<double> manual_now_{0.0};
  // Under the lock: the loop has no room to step, and when the first room of that idle
  // spell was added or woken (NaN: none yet): the loop paces from then, not from when it
  // noticed (a test's clock may have moved in between).
  bool idle_ = true;
  double resume_at_ = std::numeric_limits<double>::quiet_NaN();  // threads in acquire(): the loop lets them in between passes
  std::condition_variable idle_cv_;
  std::thread thread_;
  bool stop_ = false;
  std::vector<int> done_;       // frames since the room woke (mesh/track pacing)
  std::vector<int> next_mesh_, next_track_;
  std::vector<std::uint8_t> was_awake_, failed_;
  std::vector<double> hips_, corners_, balls_, stage_;
  // The HIP each seat's hand of this pass came from (seq, client time, occupant), written
  // into the record with the frame's CORNERs, under out_lock: never beside an older CORNER.
  std::vector<std::uint64_t> applied_seq_, applied_occupant_;
  std::vector<double> applied_time_;
  std::vector<std::uint8_t> finite_;
  // meshes for the encoder
  mutable std::mutex mesh_mutex_;
  std::condition_variable mesh_cv_;
  std::vector<MeshSnapshot> meshes_;
  bool service_flag_ = false;
};

}  // namespace cb::loop
