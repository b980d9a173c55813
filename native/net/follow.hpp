// The two streams of a relayed websocket connection, read as they pass through a gateway's
// pump (net/pump.hpp), without a websocket implementation:
//
// * ClientTap: the client's masked frames after the handshake; each whole, final binary
//   frame of at most `max_take` bytes is offered (unmasked) to a taker and dropped if
//   taken (a HIP its lane wrote into the block); every other byte goes on unchanged.
// * ServerFollow: the engine's answer and frames: whether the stream is between two
//   messages (where the gateway may write a CORNER, a MESH or a close frame of its own),
//   the room the client is in, read from the start of the engine's text messages
//   (compact JSON, keys in the order the engine writes them), the room's frame and
//   server time from the binary messages' headers and the events; and the engine's lane
//   messages (small text messages starting `{"type":"_lane"`), taken out of the stream.
//
// The Python forms they replace are in the history (server/gateway/frames.py,
// game/wire/wsframe.FrameTap); tests/server/test_pump.py holds them to the same cases.
#pragma once
#include <cstdint>
#include <cstring>
#include <functional>
#include <string>
#include <string_view>

#include "net/wsframe.hpp"

namespace cb::net {

constexpr std::size_t kHeadMax = 1 << 16;  // an HTTP head longer than this is not followed
constexpr std::size_t kPeek = 256;         // a text message's first bytes kept to read it
constexpr std::size_t kHold = 2048;        // a whole text frame up to this long is held
constexpr std::size_t kBinaryHead = 16;    // docs/protocol.md's header <BBHId
constexpr std::string_view kLanePrefix = R"({"type":"_lane")";

// Appends `n` bytes at `p` to `out`.
inline void append(std::string& out, const void* p, std::size_t n) {
  out.append(static_cast<const char*>(p), n);
}

// A frame's start not yet whole, carried from one feed to the next: `view` gives the bytes
// to read now (those carried, then the new ones), `keep` what was left unread.
class Carry {
 public:
  void view(const std::uint8_t* data, std::size_t n, const std::uint8_t*& buf,
            std::size_t& end) {
    if (partial_.empty()) {
      buf = data;
      end = n;
      return;
    }
    partial_.append(reinterpret_cast<const char*>(data), n);
    scratch_.swap(partial_);
    partial_.clear();
    buf = reinterpret_cast<const std::uint8_t*>(scratch_.data());
    end = scratch_.size();
  }
  void keep(const std::uint8_t* buf, std::size_t i, std::size_t end) {
    if (i < end) partial_.assign(reinterpret_cast<const char*>(buf + i), end - i);
    scratch_.clear();
  }
  bool empty() const { return partial_.empty(); }

 private:
  std::string partial_, scratch_;
};

class ClientTap {
 public:
  // take(payload, n): true when taken (the frame leaves the stream).
  using Take = std::function<bool(const std::uint8_t*, std::size_t)>;
  explicit ClientTap(std::size_t max_take) : max_take_(max_take) {}

  // Follows `data` and appends what goes on to `out`.
  void feed(const std::uint8_t* data, std::size_t n, std::string& out, const Take& take) {
    const std::uint8_t* buf;
    std::size_t end;
    carry_.view(data, n, buf, end);
    std::size_t i = 0;
    while (i < end) {
      if (skip_) {
        const std::size_t k = std::size_t(std::min<std::uint64_t>(skip_, end - i));
        append(out, buf + i, k);
        skip_ -= k;
        i += k;
        continue;
      }
      FrameHead h;
      if (!read_head(buf + i, end - i, h)) break;
      if (h.b0 == (kFin | kOpBinary) && h.masked && h.length <= max_take_ && !fragmented_) {
        if (end - i < h.size + h.length) break;  // held until whole
        std::uint8_t payload[64];
        const std::size_t len = std::size_t(h.length);
        if (len <= sizeof payload) {
          std::memcpy(payload, buf + i + h.size, len);
          unmask(payload, len, h.key);
          if (!take(payload, len)) append(out, buf + i, h.size + len);
        } else {
          append(out, buf + i, h.size + len);
        }
        i += h.size + len;
        continue;
      }
      if (!h.control()) fragmented_ = !h.fin();
      append(out, buf + i, h.size);
      i += h.size;
      skip_ = h.length;
    }
    carry_.keep(buf, i, end);
  }

 private:
  std::size_t max_take_;
  std::uint64_t skip_ = 0;
  bool fragmented_ = false;
  Carry carry_;
};

class ServerFollow {
 public:
  using OnLane = std::function<void(std::string_view)>;

  bool websocket = false;  // the engine answered 101: frames follow
  bool given_up = false;   // not a websocket stream: not followed
  bool closed = false;     // the engine's close frame went out
  std::string room;        // the room as the engine's JSON wrote it (quoted); empty: none
  std::int64_t frame = -1; // the room's frame and server time, as last seen
  double time = 0.0;

  // Follows `data` and appends what goes on to the client to `out` (all but lane
  // messages, and the start of a small text frame not yet whole, which a later call gives).
  void feed(const std::uint8_t* data, std::size_t n, std::string& out, const OnLane& on_lane) {
    if (given_up || closed) {
      append(out, data, n);
      return;
    }
    if (!websocket) {
      const std::size_t start = head_.size() > 3 ? head_.size() - 3 : 0;
      head_.append(reinterpret_cast<const char*>(data), n);
      const std::size_t at = head_.find("\r\n\r\n", start);
      if (at == std::string::npos) {
        given_up = head_.size() > kHeadMax;
        append(out, data, n);
        return;
      }
      websocket = head_.rfind("HTTP/1.1 101", 0) == 0 || head_.rfind("HTTP/1.0 101", 0) == 0;
      given_up = !websocket;
      const std::size_t rest = head_.size() - (at + 4);
      head_.clear();
      head_.shrink_to_fit();
      if (!websocket) {
        append(out, data, n);
        return;
      }
      append(out, data, n - rest);
      frames(data + (n - rest), rest, out, on_lane);
      return;
    }
    frames(data, n, out, on_lane);
  }

  // A binary message the gateway itself wrote to the client (a CORNER, a MESH): its
  // room's frame and time, as from the engine's.
  void sent_binary(const std::uint8_t* payload, std::size_t n) {
    if (n >= kBinaryHead) seen_binary(payload);
  }

  // Whether the gateway may write a message of its own now: a websocket stream, open,
  // between two of the engine's messages.
  bool between_messages() const {
    return websocket && !closed && !skip_ && carry_.empty() && !fragmented_;
  }

 private:
  void frames(const std::uint8_t* data, std::size_t n, std::string& out, const OnLane& on_lane) {
    const std::uint8_t* buf;
    std::size_t end;
    carry_.view(data, n, buf, end);
    std::size_t i = 0;
    for (;;) {
      if (skip_) {
        const std::size_t k = std::size_t(std::min<std::uint64_t>(skip_, end - i));
        if (peeking_) {
          const std::size_t p = std::min(k, peek_left_);
          peek_.append(reinterpret_cast<const char*>(buf + i), p);
          peek_left_ -= p;
        }
        append(out, buf + i, k);
        skip_ -= k;
        i += k;
        if (peeking_ && (!peek_left_ || !skip_)) {
          peeking_ = false;
          seen(peek_, peek_binary_);
        }
        if (skip_) break;
      }
      FrameHead h;
      if (!read_head(buf + i, end - i, h)) break;
      const std::uint8_t op = h.opcode();
      if (op == kOpText && h.fin() && !fragmented_ && h.length > 0 && h.length <= kHold) {
        const std::size_t len = std::size_t(h.length);
        if (end - i < h.size + len) break;  // held (in partial_) until whole
        const std::string_view payload(reinterpret_cast<const char*>(buf + i + h.size), len);
        if (on_lane && payload.substr(0, kLanePrefix.size()) == kLanePrefix) {
          on_lane(payload);
        } else {
          seen(std::string(payload.substr(0, kPeek)), false);
          append(out, buf + i, h.size + len);
        }
        i += h.size + len;
        continue;
      }
      if (op == kOpClose) closed = true;
      else if (op < 0x8) fragmented_ = !h.fin();
      append(out, buf + i, h.size);
      i += h.size;
      skip_ = h.length;
      if ((op == kOpText && h.length) || (op == kOpBinary && h.length >= kBinaryHead)) {
        peek_binary_ = op == kOpBinary;
        peeking_ = true;
        peek_.clear();
        peek_left_ = peek_binary_ ? kBinaryHead : std::size_t(std::min<std::uint64_t>(h.length, kPeek));
      }
    }
    carry_.keep(buf, i, end);
  }

  void seen_binary(const std::uint8_t* p) {
    std::uint32_t seq;
    double t;
    std::memcpy(&seq, p + 4, 4);
    std::memcpy(&t, p + 8, 8);
    const std::uint32_t ahead = std::uint32_t(std::uint64_t(seq) - std::uint64_t(frame));
    if (frame < 0 || ahead < (1u << 31)) {  // (not an older frame's message)
      frame = frame < 0 ? std::int64_t(seq) : frame + ahead;
      time = t;
    }
  }

  // A message's first bytes: where the client is.
  void seen(const std::string& s, bool binary) {
    if (binary) {
      if (s.size() >= kBinaryHead) seen_binary(reinterpret_cast<const std::uint8_t*>(s.data()));
      return;
    }
    static constexpr std::string_view joined = R"({"type":"joined","room":")";
    static constexpr std::string_view left = R"({"type":"left")";
    static constexpr std::string_view stopped = R"({"type":"error","code":"room_stopped")";
    static constexpr std::string_view event = R"({"type":"event","event":")";
    const std::string_view v(s);
    if (v.substr(0, joined.size()) == joined) {
      const std::size_t q = quoted_end(v, joined.size() - 1);
      if (q != std::string_view::npos) {
        room.assign(v.substr(joined.size() - 1, q - (joined.size() - 1)));
        frame = -1;  // another room's frames: from its first message on
      }
    } else if (v.substr(0, left.size()) == left || v.substr(0, stopped.size()) == stopped) {
      room.clear();
    } else if (v.substr(0, event.size()) == event) {
      // {"type":"event","event":"[a-z_]+","room":"...","frame":(\d+),"time":(number)
      std::size_t i = event.size();
      while (i < v.size() && ((v[i] >= 'a' && v[i] <= 'z') || v[i] == '_')) ++i;
      static constexpr std::string_view room_key = R"(","room":)";
      if (i == event.size() || v.substr(i, room_key.size()) != room_key) return;
      const std::size_t q = quoted_end(v, i + room_key.size());
      static constexpr std::string_view frame_key = R"(,"frame":)";
      if (q == std::string_view::npos || v.substr(q, frame_key.size()) != frame_key) return;
      std::size_t j = q + frame_key.size(), d0 = j;
      std::int64_t f = 0;
      while (j < v.size() && v[j] >= '0' && v[j] <= '9') f = f * 10 + (v[j++] - '0');
      static constexpr std::string_view time_key = R"(,"time":)";
      if (j == d0 || v.substr(j, time_key.size()) != time_key) return;
      j += time_key.size();
      std::size_t k = j;
      while (k < v.size() && std::strchr("0123456789.eE+-", v[k]) != nullptr && v[k]) ++k;
      if (k == j) return;
      frame = f;
      time = std::strtod(std::string(v.substr(j, k - j)).c_str(), nullptr);
    }
  }

  // The end (one past the closing quote) of the JSON string starting at `v[at]` (a quote),
  // else npos.
  static std::size_t quoted_end(std::string_view v, std::size_t at) {
    if (at >= v.size() || v[at] != '"') return std::string_view::npos;
    for (std::size_t i = at + 1; i < v.size(); ++i) {
      if (v[i] == '\\') ++i;
      else if (v[i] == '"') return i + 1;
    }
    return std::string_view::npos;
  }

  std::string head_, peek_;
  Carry carry_;
  std::uint64_t skip_ = 0;
  bool fragmented_ = false, peeking_ = false, peek_binary_ = false;
  std::size_t peek_left_ = 0;
};

}  // namespace cb::net
