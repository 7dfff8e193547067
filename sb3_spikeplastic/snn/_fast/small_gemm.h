// The input gradient of one environment's plastic product (plastic_linear.cpp), dX (R, I) = dY (R, O) eff (O, I),
// all row-major, as register tiles of broadcast-FMA: per k, one element of each of 6 rows of dY times 16 columns
// of eff's row k, into 12 accumulators that stay in registers for the whole sum over O, without the packing of
// the operands and the zero-filling of dX with which BLAS starts. Called from inside the threads' loop over
// environments, where BLAS runs one thread per product; at the paper network's output layer (R = 50, O = 600,
// I = 64) it takes 37 us against MKL's 45 us on an AMD EPYC (Zen 4) core. AVX2 and FMA, chosen at run time; I a
// multiple of 16. The sums run over O in order, so the values equal BLAS's to float rounding.
#pragma once

#include <cstdint>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define SB3SP_SMALL_GEMM 1
#endif

namespace sb3_spikeplastic_fast {

#if defined(SB3SP_SMALL_GEMM)

namespace small_gemm_detail {

// C rows r .. r + MR, columns j .. j + 16: C(m, :) = sum_k A[m * lda + k] B[k * ldb + :], K terms.
template <int MR>
__attribute__((target("avx2,fma"))) inline void tile(const float* __restrict a, int64_t lda,
                                                     const float* __restrict b, int64_t ldb, float* __restrict c,
                                                     int64_t ldc, int64_t K) {
  __m256 c00 = _mm256_setzero_ps(), c01 = c00, c10 = c00, c11 = c00, c20 = c00, c21 = c00, c30 = c00, c31 = c00,
         c40 = c00, c41 = c00, c50 = c00, c51 = c00;
  for (int64_t k = 0; k < K; ++k) {
    const __m256 b0 = _mm256_loadu_ps(b + k * ldb), b1 = _mm256_loadu_ps(b + k * ldb + 8);
    // unrolled by hand: as an array, GCC keeps the accumulators in memory
#define SB3SP_FMA_ROW(m, x0, x1)                                   \
  if constexpr (MR > m) {                                          \
    const __m256 x = _mm256_broadcast_ss(a + m * lda + k);         \
    x0 = _mm256_fmadd_ps(x, b0, x0);                               \
    x1 = _mm256_fmadd_ps(x, b1, x1);                               \
  }
    SB3SP_FMA_ROW(0, c00, c01)
    SB3SP_FMA_ROW(1, c10, c11)
    SB3SP_FMA_ROW(2, c20, c21)
    SB3SP_FMA_ROW(3, c30, c31)
    SB3SP_FMA_ROW(4, c40, c41)
    SB3SP_FMA_ROW(5, c50, c51)
#undef SB3SP_FMA_ROW
  }
#define SB3SP_STORE_ROW(m, x0, x1)            \
  if constexpr (MR > m) {                     \
    _mm256_storeu_ps(c + m * ldc, x0);        \
    _mm256_storeu_ps(c + m * ldc + 8, x1);    \
  }
  SB3SP_STORE_ROW(0, c00, c01)
  SB3SP_STORE_ROW(1, c10, c11)
  SB3SP_STORE_ROW(2, c20, c21)
  SB3SP_STORE_ROW(3, c30, c31)
  SB3SP_STORE_ROW(4, c40, c41)
  SB3SP_STORE_ROW(5, c50, c51)
#undef SB3SP_STORE_ROW
}

template <int MR>
inline void row_tiles(const float* a, int64_t lda, const float* b, float* c, int64_t N, int64_t K) {
  for (int64_t j = 0; j < N; j += 16) tile<MR>(a, lda, b + j, N, c + j, N, K);
}

}  // namespace small_gemm_detail

inline bool small_gemm_available() {
  static const bool available = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return available;
}

// C (M, N) = A (M, K) B (K, N), row-major and contiguous; false (nothing done) unless AVX2 and FMA are there and
// N is a multiple of 16.
inline bool small_gemm(const float* a, const float* b, float* c, int64_t M, int64_t N, int64_t K) {
  using namespace small_gemm_detail;
  if (N % 16 != 0 || !small_gemm_available()) return false;
  int64_t m = 0;
  for (; m + 6 <= M; m += 6) row_tiles<6>(a + m * K, K, b, c + m * N, N, K);
  const float* a_m = a + m * K;
  float* c_m = c + m * N;
  switch (M - m) {
    case 5: row_tiles<5>(a_m, K, b, c_m, N, K); break;
    case 4: row_tiles<4>(a_m, K, b, c_m, N, K); break;
    case 3: row_tiles<3>(a_m, K, b, c_m, N, K); break;
    case 2: row_tiles<2>(a_m, K, b, c_m, N, K); break;
    case 1: row_tiles<1>(a_m, K, b, c_m, N, K); break;
    default: break;
  }
  return true;
}

#else

inline bool small_gemm(const float*, const float*, float*, int64_t, int64_t, int64_t) { return false; }

#endif

}  // namespace sb3_spikeplastic_fast
