// Vector helpers of the trace kernels (trace_step.cpp, and the deferred trace update in plastic_linear.cpp).
#pragma once

#include <cstdint>

namespace sb3_spikeplastic_fast {

// Row sums run on a vector of partial sums held in a register (GCC's and Clang's vector extensions),
// added up pairwise at the end of the row. GCC compiles an `omp simd reduction` into partial sums kept in
// memory, loaded and stored on every iteration, whose store-to-load latency made most of these kernels' time.
// The order of the additions is fixed, so a row's result does not depend on the thread or the batch.
template <typename T>
struct Lanes;
template <>
struct Lanes<float> {
  typedef float V __attribute__((vector_size(32)));
  typedef int32_t Mask __attribute__((vector_size(32)));
  static constexpr int64_t n = 8;
};
template <>
struct Lanes<double> {
  typedef double V __attribute__((vector_size(32)));
  typedef int64_t Mask __attribute__((vector_size(32)));
  static constexpr int64_t n = 4;
};

template <typename T>
inline typename Lanes<T>::V load(const T* p) {
  typename Lanes<T>::V v;
  __builtin_memcpy(&v, p, sizeof v);
  return v;
}

template <typename T>
inline void store(T* p, typename Lanes<T>::V v) {
  __builtin_memcpy(p, &v, sizeof v);
}

template <typename T>
inline typename Lanes<T>::V splat(T x) {
  typename Lanes<T>::V v;
  for (int64_t k = 0; k < Lanes<T>::n; ++k) v[k] = x;
  return v;
}

template <typename T>
inline T sum_lanes(typename Lanes<T>::V v) {  // pairwise
  for (int64_t half = Lanes<T>::n / 2; half >= 1; half /= 2) {
    for (int64_t k = 0; k < half; ++k) v[k] += v[k + half];
  }
  return v[0];
}

template <typename scalar_t>
inline scalar_t dot(const scalar_t* __restrict a, const scalar_t* __restrict b, int64_t n) {
  constexpr int64_t W = Lanes<scalar_t>::n;
  typename Lanes<scalar_t>::V acc = splat<scalar_t>(0);
  int64_t i = 0;
  for (; i + W <= n; i += W) acc += load(a + i) * load(b + i);
  scalar_t s = sum_lanes<scalar_t>(acc);
  for (; i < n; ++i) s += a[i] * b[i];
  return s;
}

}  // namespace sb3_spikeplastic_fast
