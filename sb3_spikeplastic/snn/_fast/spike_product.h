// Products with a matrix of binary spikes (plastic_linear.cpp): the input layer's spikes X (R, I) fire at a few
// per cent, so Y = X M^T adds, per row of X, the columns of M of its firing inputs, and G = dY^T X adds, per input,
// the rows of dY at its firing steps, instead of multiplying through the zeros. Both need column access to a
// row-major operand, which 8 x 8 register transposes give at little cost. AVX2 only (the build's -mavx2); without
// it index_spikes declines and the caller keeps the dense product.
#pragma once

#include <algorithm>
#include <cstdint>
#include <vector>

#if defined(__AVX2__)
#include <immintrin.h>
#endif

namespace sb3_spikeplastic_fast {

// The firing inputs of each row of X (row r: index[start[r] .. start[r + 1])), then, for the gradient, the firing
// rows of each input (input i: rows[col_start[i] .. col_start[i + 1])), both in increasing order.
struct SpikeIndex {
  std::vector<int32_t> start, index, col_start, rows;
  std::vector<int32_t> fill;  // scratch: the next free position of each input's list
  std::vector<float> tile;    // scratch: 8 rows of the gradient's transpose
};

#if defined(__AVX2__)

namespace spike_detail {

// For each 8-bit mask, the positions of its set bits, one per byte, lowest first.
struct CompressTable {
  uint64_t v[256];
  constexpr CompressTable() : v() {
    for (int m = 0; m < 256; ++m) {
      uint64_t packed = 0;
      int n = 0;
      for (int bit = 0; bit < 8; ++bit) {
        if (m & (1 << bit)) packed |= static_cast<uint64_t>(bit) << (8 * n++);
      }
      v[m] = packed;
    }
  }
};
inline constexpr CompressTable kCompress{};

inline void transpose8(__m256& r0, __m256& r1, __m256& r2, __m256& r3, __m256& r4, __m256& r5, __m256& r6,
                       __m256& r7) {
  const __m256 t0 = _mm256_unpacklo_ps(r0, r1), t1 = _mm256_unpackhi_ps(r0, r1), t2 = _mm256_unpacklo_ps(r2, r3),
               t3 = _mm256_unpackhi_ps(r2, r3), t4 = _mm256_unpacklo_ps(r4, r5), t5 = _mm256_unpackhi_ps(r4, r5),
               t6 = _mm256_unpacklo_ps(r6, r7), t7 = _mm256_unpackhi_ps(r6, r7);
  const __m256 s0 = _mm256_shuffle_ps(t0, t2, 0x44), s1 = _mm256_shuffle_ps(t0, t2, 0xEE),
               s2 = _mm256_shuffle_ps(t1, t3, 0x44), s3 = _mm256_shuffle_ps(t1, t3, 0xEE),
               s4 = _mm256_shuffle_ps(t4, t6, 0x44), s5 = _mm256_shuffle_ps(t4, t6, 0xEE),
               s6 = _mm256_shuffle_ps(t5, t7, 0x44), s7 = _mm256_shuffle_ps(t5, t7, 0xEE);
  r0 = _mm256_permute2f128_ps(s0, s4, 0x20);
  r1 = _mm256_permute2f128_ps(s1, s5, 0x20);
  r2 = _mm256_permute2f128_ps(s2, s6, 0x20);
  r3 = _mm256_permute2f128_ps(s3, s7, 0x20);
  r4 = _mm256_permute2f128_ps(s0, s4, 0x31);
  r5 = _mm256_permute2f128_ps(s1, s5, 0x31);
  r6 = _mm256_permute2f128_ps(s2, s6, 0x31);
  r7 = _mm256_permute2f128_ps(s3, s7, 0x31);
}

// dst (8, ...) rows at stride ldd = the transpose of src (8, ...) rows at stride lds, one 8 x 8 block.
inline void transpose_block(const float* src, int64_t lds, float* dst, int64_t ldd) {
  __m256 r0 = _mm256_loadu_ps(src), r1 = _mm256_loadu_ps(src + lds), r2 = _mm256_loadu_ps(src + 2 * lds),
         r3 = _mm256_loadu_ps(src + 3 * lds), r4 = _mm256_loadu_ps(src + 4 * lds),
         r5 = _mm256_loadu_ps(src + 5 * lds), r6 = _mm256_loadu_ps(src + 6 * lds),
         r7 = _mm256_loadu_ps(src + 7 * lds);
  transpose8(r0, r1, r2, r3, r4, r5, r6, r7);
  _mm256_storeu_ps(dst, r0);
  _mm256_storeu_ps(dst + ldd, r1);
  _mm256_storeu_ps(dst + 2 * ldd, r2);
  _mm256_storeu_ps(dst + 3 * ldd, r3);
  _mm256_storeu_ps(dst + 4 * ldd, r4);
  _mm256_storeu_ps(dst + 5 * ldd, r5);
  _mm256_storeu_ps(dst + 6 * ldd, r6);
  _mm256_storeu_ps(dst + 7 * ldd, r7);
}

// y[0 : 8 NV] = the sum of the rows idx (at stride O) of MT from its column 0, in the order given.
template <int NV>
inline void add_rows(const float* MT, int64_t O, const int32_t* idx, int32_t n, float* y) {
  __m256 acc[NV];
  for (int k = 0; k < NV; ++k) acc[k] = _mm256_setzero_ps();
  int32_t j = 0;
  for (; j + 2 <= n; j += 2) {  // two rows at a time: half as long a chain of dependent additions
    const float* a = MT + static_cast<int64_t>(idx[j]) * O;
    const float* b = MT + static_cast<int64_t>(idx[j + 1]) * O;
    for (int k = 0; k < NV; ++k) {
      acc[k] = _mm256_add_ps(acc[k], _mm256_add_ps(_mm256_loadu_ps(a + 8 * k), _mm256_loadu_ps(b + 8 * k)));
    }
  }
  if (j < n) {
    const float* a = MT + static_cast<int64_t>(idx[j]) * O;
    for (int k = 0; k < NV; ++k) acc[k] = _mm256_add_ps(acc[k], _mm256_loadu_ps(a + 8 * k));
  }
  for (int k = 0; k < NV; ++k) _mm256_storeu_ps(y + 8 * k, acc[k]);
}

// y[0 : O] = the sum of the rows idx (at stride O) of MT: 64 columns at a time (8 accumulators), then 8.
inline void add_full_rows(const float* MT, int64_t O, const int32_t* idx, int32_t n, float* y) {
  int64_t o = 0;
  for (; o + 64 <= O; o += 64) add_rows<8>(MT + o, O, idx, n, y + o);
  for (; o < O; o += 8) add_rows<1>(MT + o, O, idx, n, y + o);
}

}  // namespace spike_detail

// Fills s with X's (R, I) firing inputs per row when every value is 0 or 1 and at most max_count are 1; returns
// false otherwise (another value, e.g. a filtered PSP, or too many spikes for the sparse products to pay).
inline bool index_spikes(const float* X, int64_t R, int64_t I, int64_t max_count, SpikeIndex& s) {
  s.start.resize(R + 1);
  s.index.resize(std::max<int64_t>(max_count, 0) + I + 8);  // a row may overrun the limit before it is checked
  int32_t* out = s.index.data();
  int32_t n = 0;
  const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
  for (int64_t r = 0; r < R; ++r) {
    s.start[r] = n;
    const float* x = X + r * I;
    __m256 bad = zero;
    int64_t i = 0;
    for (; i + 8 <= I; i += 8) {
      const __m256 v = _mm256_loadu_ps(x + i);
      const __m256 nz = _mm256_cmp_ps(v, zero, _CMP_NEQ_UQ);  // NaN counts as nonzero, and as not binary
      bad = _mm256_or_ps(bad, _mm256_and_ps(nz, _mm256_cmp_ps(v, one, _CMP_NEQ_UQ)));
      const unsigned m = static_cast<unsigned>(_mm256_movemask_ps(nz));
      const __m256i pos = _mm256_add_epi32(
          _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(static_cast<long long>(spike_detail::kCompress.v[m]))),
          _mm256_set1_epi32(static_cast<int>(i)));
      _mm256_storeu_si256(reinterpret_cast<__m256i*>(out + n), pos);
      n += __builtin_popcount(m);
    }
    for (; i < I; ++i) {
      if (x[i] == 0.0f) continue;
      if (x[i] != 1.0f) return false;
      out[n++] = static_cast<int32_t>(i);
    }
    if (_mm256_movemask_ps(bad) != 0 || n > max_count) return false;
  }
  s.start[R] = n;
  return true;
}

// Y (R, O) = X MT with X's spikes indexed in s and MT (I, O) row-major (M^T); O a multiple of 8.
inline void spike_product(const SpikeIndex& s, int64_t R, const float* MT, int64_t O, float* Y) {
  for (int64_t r = 0; r < R; ++r) {
    const int32_t* idx = s.index.data() + s.start[r];
    spike_detail::add_full_rows(MT, O, idx, s.start[r + 1] - s.start[r], Y + r * O);
  }
}

// MT (I, O) = the transpose of M (O, I); O a multiple of 8.
inline void transpose_rows(const float* M, int64_t O, int64_t I, float* MT) {
  for (int64_t o = 0; o < O; o += 8) {
    int64_t i = 0;
    for (; i + 8 <= I; i += 8) spike_detail::transpose_block(M + o * I + i, I, MT + i * O + o, O);
    for (; i < I; ++i) {
      for (int64_t k = 0; k < 8; ++k) MT[i * O + o + k] = M[(o + k) * I + i];
    }
  }
}

// G (O, I) = dY^T X with dY (R, O) and X's spikes indexed in s (its per-input lists filled here); O a multiple
// of 8. Row i of G^T sums dY's rows at input i's firing steps (add_full_rows, one loop per input: a loop per input and
// column block would mispredict its exit far more often); 8 such rows at a time are transposed into place.
inline void spike_gradient(SpikeIndex& s, int64_t R, int64_t I, const float* dY, int64_t O, float* G) {
  const int32_t count = s.start[R];
  s.col_start.assign(I + 1, 0);
  s.rows.resize(std::max<int32_t>(count, 1));
  for (int32_t j = 0; j < count; ++j) ++s.col_start[s.index[j] + 1];
  for (int64_t i = 0; i < I; ++i) s.col_start[i + 1] += s.col_start[i];
  s.fill.assign(s.col_start.begin(), s.col_start.end() - 1);
  for (int64_t r = 0; r < R; ++r) {
    for (int32_t j = s.start[r]; j < s.start[r + 1]; ++j) s.rows[s.fill[s.index[j]]++] = static_cast<int32_t>(r);
  }
  s.tile.resize(8 * O);
  float* tile = s.tile.data();
  for (int64_t i = 0; i < I; i += 8) {
    const int64_t n = std::min<int64_t>(8, I - i);
    for (int64_t k = 0; k < n; ++k) {
      const int32_t* rows = s.rows.data() + s.col_start[i + k];
      spike_detail::add_full_rows(dY, O, rows, s.col_start[i + k + 1] - s.col_start[i + k], tile + k * O);
    }
    for (int64_t o = 0; o < O; o += 8) {
      if (n == 8) {
        spike_detail::transpose_block(tile + o, O, G + o * I + i, I);
      } else {
        for (int64_t k = 0; k < n; ++k) {
          for (int64_t c = 0; c < 8; ++c) G[(o + c) * I + i + k] = tile[k * O + o + c];
        }
      }
    }
  }
}

#else

inline bool index_spikes(const float*, int64_t, int64_t, int64_t, SpikeIndex&) { return false; }
inline void spike_product(const SpikeIndex&, int64_t, const float*, int64_t, float*) {}
inline void transpose_rows(const float*, int64_t, int64_t, float*) {}
inline void spike_gradient(SpikeIndex&, int64_t, int64_t, const float*, int64_t, float*) {}

#endif

}  // namespace sb3_spikeplastic_fast
