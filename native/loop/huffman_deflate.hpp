// A zlib stream (RFC 1950, deflate RFC 1951) of literals alone: one dynamic-Huffman block
// per segment of the input, its code built from that segment's byte counts, no match
// search. MESH version 2's byte planes (mesh_msg.hpp) are each close to one distribution
// of bytes (a plane's low bytes near noise, its high bytes mostly zeros), so a code per
// plane takes them to about what deflate's level 1 makes of them, without the match
// finding that is most of its time on them. Any inflater reads it
// (DecompressionStream("deflate"), zlib); tests/server/test_mesh_msg.py inflates it with
// Python's zlib.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstring>

#include "third_party/libdeflate/libdeflate.h"

namespace cb::loop::huff {

constexpr int kLitSyms = 257;  // the 256 byte values and end-of-block; no lengths
constexpr int kClSyms = 19;

// Little-endian bit writer, deflate's order (first bit in the lowest bit of a byte): up to
// 56 bits gathered, then 8 bytes stored at once and the whole bytes among them kept, so
// the caller makes sure of 8 bytes to spare past what it writes (block() counts its bits
// before it writes them).
struct Bits {
  std::uint8_t* p;
  std::uint64_t buf = 0;
  int n = 0;
  void put(std::uint32_t v, int len) { buf |= std::uint64_t(v) << n, n += len; }
  void spill() {
    std::memcpy(p, &buf, 8);  // x86-64 and aarch64: little-endian
    p += n >> 3;
    buf >>= (n & 56);
    n &= 7;
  }
  void put_now(std::uint32_t v, int len) { put(v, len), spill(); }
};

// Code lengths (at most `limit` bits) of a complete prefix code for the counted symbols:
// Huffman's lengths, then JPEG's rebalancing (ITU T.81, K.3) where they pass the limit.
// Fewer than two counted symbols get two codes of one bit (inflaters refuse an incomplete
// code), the second on a symbol of count 0.
inline void code_lengths(const std::uint32_t* count, int syms, int limit, std::uint8_t* len) {
  std::uint16_t order[kLitSyms], tmp[kLitSyms];  // the counted symbols, by count ascending
  int used = 0;
  std::uint32_t most = 0;
  for (int s = 0; s < syms; ++s)
    if (count[s]) order[used++] = std::uint16_t(s), most = std::max(most, count[s]);
  std::fill(len, len + syms, std::uint8_t(0));
  if (used < 2) {
    const int a = used ? order[0] : 0;
    len[a] = 1;
    len[a == 0 ? 1 : 0] = 1;
    return;
  }
  // A stable radix sort, a byte of the count a pass (std::sort's branches cost more on
  // ~250 keys; ties stay in symbol order).
  for (int shift = 0; shift < 32 && (most >> shift) != 0; shift += 8) {
    int at[257] = {};
    for (int i = 0; i < used; ++i) ++at[((count[order[i]] >> shift) & 255u) + 1];
    for (int b = 0; b < 256; ++b) at[b + 1] += at[b];
    for (int i = 0; i < used; ++i) tmp[at[(count[order[i]] >> shift) & 255u]++] = order[i];
    std::copy(tmp, tmp + used, order);
  }
  // Huffman's tree by two queues: leaves in order, internal nodes as made (ascending).
  std::uint64_t weight[2 * kLitSyms];
  int parent[2 * kLitSyms];
  for (int i = 0; i < used; ++i) weight[i] = count[order[i]];
  int leaf = 0, node = used, next = used;
  const auto take = [&]() {
    if (leaf < used && (node >= next || weight[leaf] <= weight[node])) return leaf++;
    return node++;
  };
  while (next < 2 * used - 1) {
    const int a = take(), b = take();
    weight[next] = weight[a] + weight[b];
    parent[a] = parent[b] = next;
    ++next;
  }
  int depth[2 * kLitSyms];
  depth[next - 1] = 0;
  int bl_count[64] = {};
  int maxlen = 0;
  for (int i = next - 2; i >= 0; --i) {
    depth[i] = depth[parent[i]] + 1;
    if (i < used) {
      ++bl_count[depth[i]];
      maxlen = std::max(maxlen, depth[i]);
    }
  }
  for (int i = maxlen; i > limit; --i)
    while (bl_count[i] > 0) {
      int j = i - 2;
      while (bl_count[j] == 0) --j;
      bl_count[i] -= 2;
      bl_count[i - 1] += 1;
      bl_count[j + 1] += 2;
      bl_count[j] -= 1;
    }
  // The longest codes to the rarest symbols (order is ascending by count).
  int k = 0;
  for (int l = std::min(maxlen, limit); l >= 1; --l)
    for (int c = 0; c < bl_count[l]; ++c) len[order[k++]] = std::uint8_t(l);
}

// Canonical codes (RFC 1951, 3.2.2), bit-reversed for the little-endian writer.
inline void canonical(const std::uint8_t* len, int syms, std::uint16_t* code) {
  int bl_count[16] = {};
  for (int s = 0; s < syms; ++s) ++bl_count[len[s]];
  bl_count[0] = 0;
  int next[16] = {};
  for (int b = 1, c = 0; b < 16; ++b) {
    c = (c + bl_count[b - 1]) << 1;
    next[b] = c;
  }
  for (int s = 0; s < syms; ++s) {
    const int l = len[s];
    if (!l) continue;
    std::uint32_t c = std::uint32_t(next[l]++);
    // its l bits reversed: the 16-bit reversal by halves, then the top l bits of it
    c = ((c & 0x5555u) << 1) | ((c >> 1) & 0x5555u);
    c = ((c & 0x3333u) << 2) | ((c >> 2) & 0x3333u);
    c = ((c & 0x0F0Fu) << 4) | ((c >> 4) & 0x0F0Fu);
    c = ((c & 0x00FFu) << 8) | ((c >> 8) & 0x00FFu);
    code[s] = std::uint16_t(c >> (16 - l));
  }
}

// One final-or-not dynamic block of `n` literals; false, writing nothing, where it would
// pass `end` (8 bytes of which must be to spare).
inline bool block(Bits& out, const std::uint8_t* in, std::size_t n, bool final,
                  const std::uint8_t* end) {
  Bits w = out;  // in registers while it writes, not through the reference
  std::uint32_t h[4][256] = {};  // four counts: a run of one byte does not wait on itself
  std::size_t i = 0;
  for (; i + 4 <= n; i += 4) {
    ++h[0][in[i]];
    ++h[1][in[i + 1]];
    ++h[2][in[i + 2]];
    ++h[3][in[i + 3]];
  }
  for (; i < n; ++i) ++h[0][in[i]];
  std::uint32_t count[kLitSyms];
  for (int s = 0; s < 256; ++s) count[s] = h[0][s] + h[1][s] + h[2][s] + h[3][s];
  count[256] = 1;  // end of block
  std::uint8_t len[kLitSyms + 1];
  code_lengths(count, kLitSyms, 15, len);
  len[kLitSyms] = 1;  // the one distance code: one bit, never used (RFC 1951, 3.2.7)
  std::uint16_t code[kLitSyms];
  canonical(len, kLitSyms, code);
  // The code lengths, run-length coded with 16 (repeat the last 3-6), 17 (3-10 zeros) and
  // 18 (11-138 zeros).
  std::uint8_t rl_sym[kLitSyms + 1], rl_extra[kLitSyms + 1];
  int rl = 0;
  std::uint32_t cl_count[kClSyms] = {};
  const int all = kLitSyms + 1;
  for (int s = 0; s < all;) {
    const int l = len[s];
    int run = 1;
    while (s + run < all && len[s + run] == l) ++run;
    s += run;
    if (l == 0) {
      while (run >= 11) {
        const int r = std::min(run, 138);
        rl_sym[rl] = 18, rl_extra[rl++] = std::uint8_t(r - 11), run -= r;
      }
      if (run >= 3) rl_sym[rl] = 17, rl_extra[rl++] = std::uint8_t(run - 3), run = 0;
    } else {
      rl_sym[rl] = std::uint8_t(l), rl_extra[rl++] = 0, --run;
      while (run >= 3) {
        const int r = std::min(run, 6);
        rl_sym[rl] = 16, rl_extra[rl++] = std::uint8_t(r - 3), run -= r;
      }
    }
    while (run-- > 0) rl_sym[rl] = std::uint8_t(l), rl_extra[rl++] = 0;
  }
  for (int k = 0; k < rl; ++k) ++cl_count[rl_sym[k]];
  std::uint8_t cl_len[kClSyms];
  code_lengths(cl_count, kClSyms, 7, cl_len);
  std::uint16_t cl_code[kClSyms];
  canonical(cl_len, kClSyms, cl_code);
  static constexpr std::uint8_t kClOrder[kClSyms] = {16, 17, 18, 0, 8,  7, 9,  6, 10, 5,
                                                     11, 4,  12, 3, 13, 2, 14, 1, 15};
  int hclen = kClSyms;
  while (hclen > 4 && cl_len[kClOrder[hclen - 1]] == 0) --hclen;
  static constexpr std::uint8_t kExtraBits[kClSyms] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
                                                       0, 0, 0, 0, 0, 0, 2, 3, 7};
  // Its size in bits, known before any is written.
  std::uint64_t bits = 3 + 5 + 5 + 4 + 3 * std::uint64_t(hclen);
  for (int k = 0; k < rl; ++k) bits += cl_len[rl_sym[k]] + kExtraBits[rl_sym[k]];
  for (int s = 0; s < kLitSyms; ++s) bits += std::uint64_t(count[s]) * len[s];
  if (std::uint64_t(end - w.p) < (bits + std::uint64_t(w.n)) / 8 + 9) return false;
  w.put_now(final ? 1u : 0u, 1);
  w.put_now(2, 2);                       // dynamic Huffman codes
  w.put_now(kLitSyms - 257, 5);          // HLIT
  w.put_now(0, 5);                       // HDIST: one distance code
  w.put_now(std::uint32_t(hclen - 4), 4);
  for (int k = 0; k < hclen; ++k) w.put_now(cl_len[kClOrder[k]], 3);
  for (int k = 0; k < rl; ++k) {
    const int s = rl_sym[k];
    w.put(cl_code[s], cl_len[s]);
    w.put_now(rl_extra[k], kExtraBits[s]);
  }
  // The literals: three a store (at most 3 x 15 bits beside the 7 kept).
  std::uint32_t tab[256];
  for (int s = 0; s < 256; ++s) tab[s] = std::uint32_t(code[s]) | std::uint32_t(len[s]) << 16;
  std::size_t k = 0;
  for (; k + 3 <= n; k += 3) {
    const std::uint32_t a = tab[in[k]], b = tab[in[k + 1]], c = tab[in[k + 2]];
    w.put(a & 0xFFFFu, int(a >> 16));
    w.put(b & 0xFFFFu, int(b >> 16));
    w.put(c & 0xFFFFu, int(c >> 16));
    w.spill();
  }
  for (; k < n; ++k) w.put_now(tab[in[k]] & 0xFFFFu, int(tab[in[k]] >> 16));
  w.put_now(code[256], len[256]);
  out = w;
  return true;
}

// The zlib stream of `in` (`segments` blocks of `n / segments` bytes, the last taking the
// rest) into `out`; its size, or 0 where it does not fit in `cap` bytes.
inline std::size_t zlib_literals(const std::uint8_t* in, std::size_t n, int segments,
                                 std::uint8_t* out, std::size_t cap) {
  if (cap < 16 || segments < 1) return 0;
  out[0] = 0x78, out[1] = 0x01;  // deflate, 32 KiB window, no dictionary, check bits
  Bits w{out + 2};
  const std::uint8_t* end = out + cap - 4;  // the Adler-32 after the last block
  const std::size_t per = n / std::size_t(segments);
  for (int k = 0; k < segments; ++k) {
    const std::size_t at = per * std::size_t(k);
    if (!block(w, in + at, k + 1 == segments ? n - at : per, k + 1 == segments, end))
      return 0;
  }
  std::uint8_t* p = w.p + (w.n + 7) / 8;  // the last byte's unused bits are zeros
  const std::uint32_t a = libdeflate_adler32(1, in, n);
  p[0] = std::uint8_t(a >> 24), p[1] = std::uint8_t(a >> 16), p[2] = std::uint8_t(a >> 8),
  p[3] = std::uint8_t(a);
  return std::size_t(p + 4 - out);
}

}  // namespace cb::loop::huff
