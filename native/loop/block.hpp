// The frame loop's memory block: every input and output of the native frame loop
// (native/loop/frame_loop.hpp) in one allocation that another process can map read/write
// (a memfd: /proc/PID/fd/FD, or the fd passed over a socket). The one definition of its
// layout; docs/frameloop.md describes it and Python reads it through offsets the binding
// exports from here (clothball._native.frame_block_layout), never a second copy.
//
// Layout: a Header at offset 0, then `rooms` RoomRecords from rooms_offset (room_bytes
// each), then one EngineRecord at engine_offset. Plain numbers only: no pointers, no
// Python objects. Words that two threads (or processes) share are accessed with atomic
// operations (the GCC/Clang __atomic builtins: C++17 has no atomic_ref); a record part written by one side and read by the other as
// a whole is guarded by a sequence lock (odd while being written).
#pragma once
#include <cstddef>
#include <cstdint>

#include "loop/corner_msg.hpp"

namespace cb::loop {

constexpr std::uint64_t kBlockMagic = 0x314B4C42544F4C43ULL;  // "CLOTBLK1", little-endian
constexpr std::uint32_t kBlockVersion = 3;  // 2: corner_msg; 3: seat_occupant, lane access
constexpr int kSeats = 4;
constexpr int kTrackRing = 64;           // TRACK samples a room keeps (0.64 s at 100 Hz)
constexpr int kLatenessRing = 100000;    // the engine's newest lateness samples (s)

// Events: bits of RoomRecord::events, set by the loop, taken (cleared) by the reader.
enum Event : std::uint32_t {
  kEventCorner = 1,  // a frame at or past corner_due is published
  kEventExit = 2,    // the ball left the cloth while armed (exit_*); the room is disarmed
  kEventFailed = 4,  // the state turned non-finite (fail_frame); the room is no longer stepped
  kEventMesh = 8,    // a mesh snapshot is ready (FrameLoop::take_meshes)
};

struct alignas(64) Header {
  std::uint64_t magic;
  std::uint32_t version;
  std::uint32_t header_bytes;
  std::uint32_t rooms;         // RoomRecords in the block
  std::uint32_t room_bytes;    // sizeof(RoomRecord)
  std::uint32_t engine_bytes;  // sizeof(EngineRecord)
  std::uint32_t lateness_capacity;
  std::uint64_t rooms_offset;
  std::uint64_t engine_offset;
  std::uint64_t total_bytes;
  double frame_dt;   // s
  double epoch;      // CLOCK_MONOTONIC seconds of server time 0
};
// 128 bytes, so that the records after it keep their 64-byte alignment.
static_assert(sizeof(Header) == 128, "Header is 128 bytes");

struct alignas(64) RoomRecord {
  // --- written by the network side (Python, later gateways) --------------------------------
  std::uint32_t hip_lock[kSeats];      // sequence lock of each seat's hand below
  std::uint32_t hip_has[kSeats];       // 1: the seat has a hand, 0: its corner rests at anchor
  std::uint64_t hip_seq[kSeats];       // that HIP's seq
  double hip_time[kSeats];             // and client time
  std::uint64_t hip_occupant[kSeats];  // the occupant the hand belongs to
  // The seat's occupant now (written by the engine only; numbers are unique in an engine):
  // the loop applies a hand only where hip_occupant is it, so a hand written late by a
  // gateway for an occupant that has left (or for a room that left the slot) is ignored.
  std::uint64_t seat_occupant[kSeats];
  double hip_pos[kSeats][3];           // m
  std::uint32_t used;                  // 1: a room is on this slot
  std::uint32_t awake;                 // 1: stepped (0: sleeps, keeps its state)
  std::uint32_t armed;                 // 1: an exit ends the round (the loop clears it)
  std::uint32_t recording;             // 1: TRACK samples are kept (track ring)
  double corner_due;                   // server time from which a CORNER is wanted
  // --- written by the loop, under out_lock -------------------------------------------------
  std::uint32_t out_lock;
  std::uint32_t substeps;              // of the newest pass
  std::int64_t frame;                  // frames stepped since the room was added
  std::int64_t steps;                  // passes the room was stepped in
  std::int64_t skipped;                // frames dropped for being too far behind
  double server_time;                  // s, when the newest frame was published
  double corner_pos[kSeats][3];
  double corner_vel[kSeats][3];
  double force[kSeats][3];             // -K (hip - corner), N
  double ball[6];                      // position, velocity
  double hips[kSeats][3];              // the hands the newest frame used
  std::uint64_t applied_seq[kSeats];   // the HIP each seat's newest frame applied (0: none)
  double applied_time[kSeats];         // (NaN: none)
  std::uint64_t applied_occupant[kSeats];  // whose hand it was (the seat's occupant then)
  // each seat's CORNER message of the newest frame, as sent (corner_msg.hpp)
  std::uint8_t corner_msg[kSeats][kCornerBytes];
  // --- events (atomic), and what they say ----------------------------------------------------
  std::uint32_t events;
  std::int32_t exit_edge;              // the edge of the newest exit
  std::int64_t exit_frame;
  double exit_ball[3];
  std::int64_t fail_frame;
  // --- TRACK samples while recording: a ring written by the loop --------------------------
  std::uint64_t track_count;           // samples written since the room was added
  // each: frame, server_time, ball (6), hips (12), corner positions (12)
  double track[kTrackRing][32];
};

struct alignas(64) EngineRecord {
  std::int64_t passes;          // step calls, all rooms at once
  std::int64_t skipped;         // frames dropped for being too far behind (all rooms)
  std::int64_t live;            // rooms stepped in the newest pass
  std::uint64_t lateness_count; // samples written since the start (or the last clear)
  double lateness[kLatenessRing];  // s, per pass: when its state was ready against its time
};

inline std::size_t block_bytes(int rooms) {
  return sizeof(Header) + sizeof(RoomRecord) * std::size_t(rooms) + sizeof(EngineRecord);
}
inline std::size_t rooms_offset() { return sizeof(Header); }
inline std::size_t engine_offset(int rooms) {
  return sizeof(Header) + sizeof(RoomRecord) * std::size_t(rooms);
}

// Atomic access to a word of the block (a plain field, shared across threads/processes).
template <class T>
inline T load(const T& x) {
  T v;
  __atomic_load(&x, &v, __ATOMIC_ACQUIRE);
  return v;
}
template <class T>
inline void store(T& x, T v) {
  __atomic_store(&x, &v, __ATOMIC_RELEASE);
}
inline void fence() { __atomic_thread_fence(__ATOMIC_SEQ_CST); }

// A seat's hand lock: a sequence lock (odd while written) taken with a compare-and-swap,
// since two processes may write one seat (the engine when the seat changes hands, a gateway
// with its player's HIPs). A process killed while holding it must not stop the others: an
// odd value that stays for kLockSpins reads is taken as its writer's death and released
// (a writer merely descheduled that long loses one hand to a torn read at worst).
constexpr int kLockSpins = 1 << 20;
inline std::uint32_t lock_hand(RoomRecord& r, int seat) {
  std::uint32_t stuck = 0;
  int spins = 0;
  for (;;) {
    std::uint32_t v = load(r.hip_lock[seat]);
    if (v & 1u) {
      if (v != stuck) {
        stuck = v;
        spins = 0;
      } else if (++spins >= kLockSpins) {
        __atomic_compare_exchange_n(&r.hip_lock[seat], &v, v + 1, false, __ATOMIC_ACQ_REL,
                                    __ATOMIC_RELAXED);
        spins = 0;
      }
      continue;
    }
    if (__atomic_compare_exchange_n(&r.hip_lock[seat], &v, v + 1, false, __ATOMIC_ACQUIRE,
                                    __ATOMIC_RELAXED))
      return v;
  }
}
inline void unlock_hand(RoomRecord& r, int seat, std::uint32_t v) {
  store(r.hip_lock[seat], v + 2);
}

// A hand for `seat` (pos: 3 doubles), written only while `occupant` holds the seat (a
// gateway's HIP; the engine changes seat_occupant when the seat changes hands). False:
// the occupant no longer holds it, nothing written.
inline bool write_hand(RoomRecord& r, int seat, std::uint64_t occupant, const double* pos,
                       std::uint64_t seq, double time) {
  const std::uint32_t v = lock_hand(r, seat);
  const bool held = r.seat_occupant[seat] == occupant;
  if (held) {
    for (int d = 0; d < 3; ++d) r.hip_pos[seat][d] = pos[d];
    r.hip_seq[seat] = seq;
    r.hip_time[seat] = time;
    r.hip_occupant[seat] = occupant;
    r.hip_has[seat] = 1;
  }
  unlock_hand(r, seat, v);
  return held;
}

// The seat's CORNER message of the newest frame, that frame, and the occupant whose hand the
// frame applied (read together under out_lock): what a lane sends its player, when the
// occupant is the lane's (a CORNER made from a former occupant's hand echoes its HIP).
inline std::int64_t read_corner(const RoomRecord& r, int seat, std::uint8_t* out,
                                std::uint64_t& occupant) {
  for (;;) {
    const std::uint32_t v0 = load(r.out_lock);
    if (v0 & 1u) continue;
    const std::int64_t frame = r.frame;
    occupant = r.applied_occupant[seat];
    for (int b = 0; b < kCornerBytes; ++b) out[b] = r.corner_msg[seat][b];
    fence();
    if (load(r.out_lock) == v0) return frame;
  }
}

// One field of a record for the Python side's structured view: name, byte offset, NumPy
// type code, element count (1: a scalar, else a flat array; shape in the doc).
struct Field {
  const char* name;
  std::size_t offset;
  const char* type;
  int count;
  int dims[2];
};

#define CB_FIELD(S, f, t, n, d0, d1) Field{#f, offsetof(S, f), t, n, {d0, d1}}
inline const Field* room_fields(int* count) {
  static const Field f[] = {
      CB_FIELD(RoomRecord, hip_lock, "u4", 4, 4, 0),
      CB_FIELD(RoomRecord, hip_has, "u4", 4, 4, 0),
      CB_FIELD(RoomRecord, hip_seq, "u8", 4, 4, 0),
      CB_FIELD(RoomRecord, hip_time, "f8", 4, 4, 0),
      CB_FIELD(RoomRecord, hip_occupant, "u8", 4, 4, 0),
      CB_FIELD(RoomRecord, seat_occupant, "u8", 4, 4, 0),
      CB_FIELD(RoomRecord, hip_pos, "f8", 12, 4, 3),
      CB_FIELD(RoomRecord, used, "u4", 1, 0, 0),
      CB_FIELD(RoomRecord, awake, "u4", 1, 0, 0),
      CB_FIELD(RoomRecord, armed, "u4", 1, 0, 0),
      CB_FIELD(RoomRecord, recording, "u4", 1, 0, 0),
      CB_FIELD(RoomRecord, corner_due, "f8", 1, 0, 0),
      CB_FIELD(RoomRecord, out_lock, "u4", 1, 0, 0),
      CB_FIELD(RoomRecord, substeps, "u4", 1, 0, 0),
      CB_FIELD(RoomRecord, frame, "i8", 1, 0, 0),
      CB_FIELD(RoomRecord, steps, "i8", 1, 0, 0),
      CB_FIELD(RoomRecord, skipped, "i8", 1, 0, 0),
      CB_FIELD(RoomRecord, server_time, "f8", 1, 0, 0),
      CB_FIELD(RoomRecord, corner_pos, "f8", 12, 4, 3),
      CB_FIELD(RoomRecord, corner_vel, "f8", 12, 4, 3),
      CB_FIELD(RoomRecord, force, "f8", 12, 4, 3),
      CB_FIELD(RoomRecord, ball, "f8", 6, 6, 0),
      CB_FIELD(RoomRecord, hips, "f8", 12, 4, 3),
      CB_FIELD(RoomRecord, applied_seq, "u8", 4, 4, 0),
      CB_FIELD(RoomRecord, applied_time, "f8", 4, 4, 0),
      CB_FIELD(RoomRecord, applied_occupant, "u8", 4, 4, 0),
      CB_FIELD(RoomRecord, corner_msg, "u1", kSeats * kCornerBytes, kSeats, kCornerBytes),
      CB_FIELD(RoomRecord, events, "u4", 1, 0, 0),
      CB_FIELD(RoomRecord, exit_edge, "i4", 1, 0, 0),
      CB_FIELD(RoomRecord, exit_frame, "i8", 1, 0, 0),
      CB_FIELD(RoomRecord, exit_ball, "f8", 3, 3, 0),
      CB_FIELD(RoomRecord, fail_frame, "i8", 1, 0, 0),
      CB_FIELD(RoomRecord, track_count, "u8", 1, 0, 0),
      CB_FIELD(RoomRecord, track, "f8", kTrackRing * 32, kTrackRing, 32),
  };
  *count = int(sizeof(f) / sizeof(f[0]));
  return f;
}
inline const Field* engine_fields(int* count) {
  static const Field f[] = {
      CB_FIELD(EngineRecord, passes, "i8", 1, 0, 0),
      CB_FIELD(EngineRecord, skipped, "i8", 1, 0, 0),
      CB_FIELD(EngineRecord, live, "i8", 1, 0, 0),
      CB_FIELD(EngineRecord, lateness_count, "u8", 1, 0, 0),
      CB_FIELD(EngineRecord, lateness, "f8", kLatenessRing, kLatenessRing, 0),
  };
  *count = int(sizeof(f) / sizeof(f[0]));
  return f;
}
#undef CB_FIELD

}  // namespace cb::loop
