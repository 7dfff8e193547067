// The plastic layer's synaptic product (CPU fast path of sb3_spikeplastic.snn.functional.project):
//
//     Y[b] = X[b] (W + alpha * E[b])^T          X (B, R, n_in), W, alpha (n_out, n_in), E (B, n_out, n_in)
//
// Eager PyTorch materialises the per-environment efficacy W_eff (B, n_out, n_in) for a batched matmul, and in
// the backward its gradient dW_eff of the same size, then reads both again for dW, dalpha and dE: four extra
// passes over trace-sized arrays. Here the efficacy (or its gradient) of a block of a few environments is built
// in a buffer that stays in cache (at most ~256 KB), used by one batched matrix product and overwritten by the next
// block's; a block, not one environment, because each at::bmm_out call costs microseconds of dispatch, which at
// the CPU entry's sizes (16 environments, 12 x 170 x 64) was most of the layer's time. Where a block holds one
// environment (the paper network's 600 x 64 layers), its products call BLAS directly instead (gemm below), and its
// input gradient runs a register-tiled kernel of ours where the CPU has FMA (small_gemm.h: faster than BLAS at
// these shapes, on one thread):
//
//     forward:   eff = W + alpha * E[b];          Y[b] = X[b] eff^T
//     backward:  G = dY[b]^T X[b]                 (the gradient of W_eff[b], in W's layout)
//
// Rows carried beside X (C (B, 2, n_in): a layer's PSP state, the rows it would otherwise append to the interval's
// spikes with a copy of them all) are multiplied in the pass that builds the efficacy, Yc[b] = C[b] eff^T as row
// sums, and their part of G, dYc[b]^T C[b], is added in the backward pass over G.
//                dE[b] = alpha * G (+ dE_init[b]),  dW += G,  dalpha += E[b] * G    (one pass over G and E[b],
//                                                         which also writes the efficacy over G when dX is needed)
//                dX[b] = dY[b] (W + alpha * E[b])                         (only when X needs a gradient)
//
// Environments are independent, so they are split between threads (dW and dalpha are summed per thread, then
// added; a thread's first row fills its sums, so they are not zero-filled first).
//
// Where X[b] is binary spikes firing at most at spike_density_limit (30 %; the input layer's place cells: ~10 %), the
// forward and gradient products of a one-environment block add up the efficacy's columns of the firing inputs and
// dY's rows at each input's firing steps instead (spike_product.h; 2-3 times as fast at 10 %); any other X, or
// more spikes, takes the dense product, the tested reference.
//
// Equal to the eager ops to float rounding (sums run in another order).

#include <ATen/Context.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/grad_mode.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/bmm.h>
#include <ATen/ops/zeros.h>
#include <c10/core/ScalarType.h>
#include <torch/library.h>

#include "denormal_mode.h"
#include "kernels.h"
#include "lanes.h"
#include "small_gemm.h"
#include "spike_product.h"

#include <algorithm>
#include <atomic>
#include <optional>
#include <tuple>
#include <type_traits>
#include <vector>

// BLAS's own matrix product, which torch's MKL build exports (LP64). Declared weak: where the library does not
// export it (other BLAS builds) these are null and the products go through at::bmm_out instead.
extern "C" {
void sgemm_(const char* transa, const char* transb, const int* m, const int* n, const int* k, const float* alpha,
            const float* a, const int* lda, const float* b, const int* ldb, const float* beta, float* c,
            const int* ldc) __attribute__((weak));
void dgemm_(const char* transa, const char* transb, const int* m, const int* n, const int* k, const double* alpha,
            const double* a, const int* lda, const double* b, const int* ldb, const double* beta, double* c,
            const int* ldc) __attribute__((weak));
}

namespace {

// Whether gemm<scalar_t> can call BLAS directly, for blocks of one environment: a function call where
// at::bmm_out adds dispatch, views and checks to each environment's product (the paper network's training pass:
// ~5 % of its time). MKL only: called from the pool's threads, it runs single-threaded inside their parallel
// region, which other BLAS libraries need not do.
template <typename scalar_t>
bool has_blas() {
  static const bool mkl = at::globalContext().hasMKL();
  if constexpr (std::is_same_v<scalar_t, float>) {
    return mkl && sgemm_ != nullptr;
  } else {
    return mkl && dgemm_ != nullptr;
  }
}

// The largest fraction of X[b]'s values that may be spikes for the spike products (benchmarks/README.md, "Products
// on spikes": at the paper network's 600 -> 64 sizes the forward product breaks even at ~35 % and the gradient at
// ~45 %), and how many environments' products took each path since the library was loaded (spike, dense).
std::atomic<double> spike_density_limit{0.3};
std::atomic<int64_t> spike_products{0}, dense_products{0};

// X[b] (R, I) indexed in s when it is binary and sparse enough (then counted as a spike product, else as dense).
bool index_environment(const float* X, int64_t R, int64_t I, sb3_spikeplastic_fast::SpikeIndex& s) {
  const auto limit = static_cast<int64_t>(spike_density_limit.load() * static_cast<double>(R * I));
  const bool sparse = sb3_spikeplastic_fast::index_spikes(X, R, I, limit, s);
  (sparse ? spike_products : dense_products).fetch_add(1, std::memory_order_relaxed);
  return sparse;
}

// Whether the spike products may apply: float32 blocks of one environment, n_out a multiple of the vector width.
template <typename scalar_t>
bool spike_block(int64_t n, int64_t O) {
  return std::is_same_v<scalar_t, float> && n == 1 && O % 8 == 0 && spike_density_limit.load() > 0;
}

// Y[b] (R, O) = X[b] eff^T as a spike product, eff (O, I) the block's efficacy; false where it does not apply (the
// caller then takes the dense product).
template <typename scalar_t>
bool spike_block_forward(const at::Tensor& X, at::Tensor& Y, const scalar_t* eff, int64_t b, int64_t n) {
  if constexpr (std::is_same_v<scalar_t, float>) {
    const int64_t R = X.size(1), I = X.size(2), O = Y.size(2);
    static thread_local sb3_spikeplastic_fast::SpikeIndex spikes;
    static thread_local std::vector<float> effT;
    if (!spike_block<scalar_t>(n, O) || !index_environment(X.data_ptr<float>() + b * R * I, R, I, spikes)) {
      return false;
    }
    effT.resize(I * O);
    sb3_spikeplastic_fast::transpose_rows(eff, O, I, effT.data());
    sb3_spikeplastic_fast::spike_product(spikes, R, effT.data(), O, Y.data_ptr<float>() + b * R * O);
    return true;
  }
  return false;
}

// G (O, I) = dY[b]^T X[b] as a spike product; false where it does not apply.
template <typename scalar_t>
bool spike_block_gradient(const at::Tensor& dY, const at::Tensor& X, at::Tensor& G, int64_t b, int64_t n) {
  if constexpr (std::is_same_v<scalar_t, float>) {
    const int64_t R = X.size(1), I = X.size(2), O = dY.size(2);
    static thread_local sb3_spikeplastic_fast::SpikeIndex spikes;
    if (!spike_block<scalar_t>(n, O) || !index_environment(X.data_ptr<float>() + b * R * I, R, I, spikes)) {
      return false;
    }
    sb3_spikeplastic_fast::spike_gradient(spikes, R, I, dY.data_ptr<float>() + b * R * O, O, G.data_ptr<float>());
    return true;
  }
  return false;
}

// Column-major C (m, n) = op(A) op(B), BLAS's convention; a row-major (r, c) matrix is a column-major (c, r) one.
template <typename scalar_t>
void gemm(char transa, char transb, int64_t m, int64_t n, int64_t k, const scalar_t* a, int64_t lda,
          const scalar_t* b, int64_t ldb, scalar_t* c, int64_t ldc) {
  const int m_ = static_cast<int>(m), n_ = static_cast<int>(n), k_ = static_cast<int>(k);
  const int lda_ = static_cast<int>(lda), ldb_ = static_cast<int>(ldb), ldc_ = static_cast<int>(ldc);
  const scalar_t one = 1, zero = 0;
  if constexpr (std::is_same_v<scalar_t, float>) {
    sgemm_(&transa, &transb, &m_, &n_, &k_, &one, a, &lda_, b, &ldb_, &zero, c, &ldc_);
  } else {
    dgemm_(&transa, &transb, &m_, &n_, &k_, &one, a, &lda_, b, &ldb_, &zero, c, &ldc_);
  }
}

// The three products of a block of n environments from b0 (one gemm for one environment, else at::bmm_out; the
// input gradient of one float32 environment by small_gemm where it applies), with buf the block's (n, O, I)
// efficacy or efficacy gradient:
//     forward   Y[b] (R, O) = X[b] (R, I) eff^T
//     gradient  buf (O, I) = dY[b]^T (O, R) X[b] (R, I)
//     input     dX[b] (R, I) = dY[b] (R, O) eff (O, I)
template <typename scalar_t>
void block_forward(bool blas, const at::Tensor& X, at::Tensor& Y, const at::Tensor& buf, int64_t b0, int64_t n) {
  const int64_t R = X.size(1), I = X.size(2), O = Y.size(2);
  if (blas && n == 1) {
    gemm<scalar_t>('T', 'N', O, R, I, buf.data_ptr<scalar_t>(), I, X.data_ptr<scalar_t>() + b0 * R * I, I,
                   Y.data_ptr<scalar_t>() + b0 * R * O, O);
  } else {
    at::Tensor y = Y.narrow(0, b0, n);
    at::bmm_out(y, X.narrow(0, b0, n), buf.narrow(0, 0, n).transpose(1, 2));
  }
}

template <typename scalar_t>
void block_gradient(bool blas, const at::Tensor& dY, const at::Tensor& X, at::Tensor& buf, int64_t b0, int64_t n) {
  const int64_t R = X.size(1), I = X.size(2), O = dY.size(2);
  if (blas && n == 1) {
    gemm<scalar_t>('N', 'T', I, O, R, X.data_ptr<scalar_t>() + b0 * R * I, I, dY.data_ptr<scalar_t>() + b0 * R * O,
                   O, buf.data_ptr<scalar_t>(), I);
  } else {
    at::Tensor G_n = buf.narrow(0, 0, n);
    at::bmm_out(G_n, dY.narrow(0, b0, n).transpose(1, 2), X.narrow(0, b0, n));
  }
}

template <typename scalar_t>
void block_input_gradient(bool blas, const at::Tensor& dY, const at::Tensor& buf, at::Tensor& dX, int64_t b0,
                          int64_t n) {
  const int64_t R = dX.size(1), I = dX.size(2), O = dY.size(2);
  if constexpr (std::is_same_v<scalar_t, float>) {
    if (n == 1 && sb3_spikeplastic_fast::small_gemm(dY.data_ptr<float>() + b0 * R * O, buf.data_ptr<float>(),
                                                    dX.data_ptr<float>() + b0 * R * I, R, I, O)) {
      return;
    }
  }
  if (blas && n == 1) {
    gemm<scalar_t>('N', 'N', I, R, O, buf.data_ptr<scalar_t>(), I, dY.data_ptr<scalar_t>() + b0 * R * O, O,
                   dX.data_ptr<scalar_t>() + b0 * R * I, I);
  } else {
    at::Tensor dx = dX.narrow(0, b0, n);
    at::bmm_out(dx, dY.narrow(0, b0, n), buf.narrow(0, 0, n));
  }
}

// The backward passes' loop over blocks, split between torch's threads: body(b0, n, G, dw, da, first) for each
// block, with G a (nb, O, I) buffer of the thread's, dw and da its sums of dW and dalpha in acc (threads, 2, O, I),
// which a thread's first row fills (first) and later ones add to; used marks the threads that wrote theirs.
template <typename scalar_t, typename Body>
void backward_blocks(int64_t B, int64_t nb, const at::Tensor& like, at::Tensor& acc, std::vector<char>& used,
                     const Body& body) {
  const int64_t O = acc.size(2), I = acc.size(3), N = O * I, blocks = (B + nb - 1) / nb;
  scalar_t* acc_p = acc.data_ptr<scalar_t>();
  const CallerDenormalMode mode;
  at::parallel_for(0, blocks, 1, [&](int64_t begin, int64_t end) {
    const DenormalModeScope denormals(mode);
    at::NoGradGuard no_grad;  // grad mode is per thread: the pool's threads would record the products
    const int64_t tid = at::get_thread_num();
    scalar_t* dw = acc_p + tid * 2 * N;
    bool first = used[tid] == 0;
    used[tid] = 1;
    at::Tensor G = at::empty({nb, O, I}, like.options());
    for (int64_t block = begin; block < end; ++block) {
      const int64_t b0 = block * nb;
      body(b0, std::min(nb, B - b0), G, dw, dw + N, first);
    }
  });
}

// The deferred form's scalars and operands as its row kernels take them: eta, keep = 1 - eta and the clip bounds in
// the trace's type (as trace_step.cpp rounds them), then W, alpha, E, the pending updates' p and q (first, then
// second) and the Oja term's q (null where undefined).
template <typename scalar_t>
struct DeferredOperands {
  scalar_t eta, keep, lo, hi;
  const scalar_t *w, *a, *e, *p0, *q0, *p1, *q1, *q;
};

template <typename scalar_t>
DeferredOperands<scalar_t> deferred_operands(const at::Tensor& W, const at::Tensor& alpha, const at::Tensor& E,
                                             const at::Tensor& p0, const at::Tensor& q0, const at::Tensor& p1,
                                             const at::Tensor& q1, const at::Tensor& q, double eta, double e_max) {
  auto ptr = [](const at::Tensor& t) { return t.defined() ? t.data_ptr<scalar_t>() : nullptr; };
  const scalar_t eta_s = static_cast<scalar_t>(eta), hi = static_cast<scalar_t>(e_max);
  return {eta_s, scalar_t(1) - eta_s, -hi, hi, ptr(W), ptr(alpha), ptr(E), ptr(p0), ptr(q0), ptr(p1), ptr(q1), ptr(q)};
}

// The per-thread sums (threads, 2, O, I) of dW and dalpha added up over the threads that wrote theirs ->
// (2, O, I) (zeros when none did: an empty batch).
at::Tensor thread_sums(const at::Tensor& acc, const std::vector<char>& used) {
  at::Tensor sums;
  for (int64_t t = 0; t < acc.size(0); ++t) {
    if (!used[t]) continue;
    if (!sums.defined()) {
      sums = acc.select(0, t);
    } else {
      sums.add_(acc.select(0, t));
    }
  }
  return sums.defined() ? sums : at::zeros({2, acc.size(2), acc.size(3)}, acc.options());
}

void check_operands(const at::Tensor& X, const at::Tensor& W, const at::Tensor& alpha, const at::Tensor& E) {
  TORCH_CHECK(X.dim() == 3 && W.dim() == 2 && E.dim() == 3 && W.sizes() == alpha.sizes() && E.size(0) == X.size(0) &&
                  E.size(1) == W.size(0) && E.size(2) == W.size(1) && X.size(2) == W.size(1),
              "plastic_linear: X (B, L, i), W and alpha (o, i), E (B, o, i)");
  const auto dtype = E.scalar_type();
  TORCH_CHECK((dtype == at::kFloat || dtype == at::kDouble) && X.scalar_type() == dtype && W.scalar_type() == dtype &&
                  alpha.scalar_type() == dtype,
              "plastic_linear: float32 or float64 tensors of one dtype");
}

// Environments per block: the block's efficacy buffer stays below kBlockElements values (256 KB in float32, so it
// stays in L2 between being written and being multiplied), and the number of blocks is a multiple of the thread
// count, so that the threads get equal shares.
constexpr int64_t kBlockElements = 1 << 16;

int64_t block_size(int64_t batch, int64_t n) {
  const int64_t threads = std::max<int64_t>(1, at::get_num_threads());
  const int64_t cap = std::max<int64_t>(1, kBlockElements / std::max<int64_t>(1, n));
  int64_t blocks = (batch + cap - 1) / cap;
  blocks = std::min(batch, (blocks + threads - 1) / threads * threads);
  return std::max<int64_t>(1, (batch + blocks - 1) / std::max<int64_t>(1, blocks));
}

// A row's pending trace updates, oldest first: after the first the trace row is v = clamp(keep e + ep0 q0, +-e_max),
// after the second v = clamp(keep v + ep1 q1, +-e_max), each computed as trace_step.cpp's forward_row computes it,
// so the values are those of one trace step after the other, bit for bit. Unused entries are null.
template <typename T>
struct PendingRow {
  const T* q0;
  T ep0;
  const T* q1;
  T ep1;
};

template <typename V>
inline V clamp_lanes(V x, V lo, V hi) {
  return x < lo ? lo : (x > hi ? hi : x);
}

// The pending-update count (0, 1 or 2) and whether the trace is written, as template arguments of f.
template <typename F>
void with_pending(int64_t pending, bool write, const F& f) {
  using none = std::integral_constant<int, 0>;
  using one = std::integral_constant<int, 1>;
  using two = std::integral_constant<int, 2>;
  if (pending == 0) {
    f(none{}, std::false_type{});
  } else if (pending == 1) {
    write ? f(one{}, std::true_type{}) : f(one{}, std::false_type{});
  } else {
    write ? f(two{}, std::true_type{}) : f(two{}, std::false_type{});
  }
}

// Row sums of the deferred forward pass: the Oja term's v . q and the carried rows' products eff . c0, eff . c1.
template <typename T>
struct RowSums {
  T q = 0, c0 = 0, c1 = 0;
};

// One row of the deferred forward pass (plastic_linear_deferred_forward): the trace row v the product uses (e0 with
// the pending updates applied), written to et when write, and the efficacy's row w + a v to eff; returns the row
// sums (v . q without q and the carried rows' without them are 0).
template <typename T, int pending, bool write, bool carried>
inline RowSums<T> deferred_row(const T* __restrict e0, const PendingRow<T>& u, T keep, T lo, T hi,
                               const T* __restrict w, const T* __restrict a, const T* __restrict q,
                               const T* __restrict c0, const T* __restrict c1, T* __restrict et, T* __restrict eff,
                               int64_t n) {
  using sb3_spikeplastic_fast::load;
  using sb3_spikeplastic_fast::splat;
  using sb3_spikeplastic_fast::store;
  using V = typename sb3_spikeplastic_fast::Lanes<T>::V;
  constexpr int64_t L = sb3_spikeplastic_fast::Lanes<T>::n;
  const V keep_v = splat(keep), ep0_v = splat(u.ep0), ep1_v = splat(u.ep1), lo_v = splat(lo), hi_v = splat(hi);
  V acc = splat<T>(0), acc0 = splat<T>(0), acc1 = splat<T>(0);
  int64_t i = 0;
  for (; i + L <= n; i += L) {
    V v = load(e0 + i);
    if constexpr (pending >= 1) v = clamp_lanes(v * keep_v + ep0_v * load(u.q0 + i), lo_v, hi_v);
    if constexpr (pending == 2) v = clamp_lanes(v * keep_v + ep1_v * load(u.q1 + i), lo_v, hi_v);
    if constexpr (write) store(et + i, v);
    const V ev = load(w + i) + load(a + i) * v;
    store(eff + i, ev);
    if (q != nullptr) acc += v * load(q + i);
    if constexpr (carried) {
      acc0 += ev * load(c0 + i);
      acc1 += ev * load(c1 + i);
    }
  }
  RowSums<T> sums;
  if (q != nullptr) sums.q = sb3_spikeplastic_fast::sum_lanes<T>(acc);
  if constexpr (carried) {
    sums.c0 = sb3_spikeplastic_fast::sum_lanes<T>(acc0);
    sums.c1 = sb3_spikeplastic_fast::sum_lanes<T>(acc1);
  }
  for (; i < n; ++i) {
    T v = e0[i];
    if constexpr (pending >= 1) v = std::min(hi, std::max(lo, v * keep + u.ep0 * u.q0[i]));
    if constexpr (pending == 2) v = std::min(hi, std::max(lo, v * keep + u.ep1 * u.q1[i]));
    if constexpr (write) et[i] = v;
    eff[i] = w[i] + a[i] * v;
    if (q != nullptr) sums.q += v * q[i];
    if constexpr (carried) {
      sums.c0 += eff[i] * c0[i];
      sums.c1 += eff[i] * c1[i];
    }
  }
  return sums;
}

// Sums of one row of the deferred backward pass, per pending update k: dL/dep_k (gx_k . q_k) and dL/dkeep_k
// (gx_k . the trace row it was applied to).
template <typename T>
struct PendingSums {
  T ep0 = 0, keep0 = 0, ep1 = 0, keep1 = 0;
};

// One row of the deferred backward pass, with g the row of the efficacy's gradient dY^T X and v1, v as in
// deferred_row (v1: the trace row after the first pending update, v: after all of them):
//
//     g <- g + dyc0 c0 + dyc1 c1          (the carried rows' part of the efficacy's gradient, when given)
//     total = a g + dr q (+ d1 when the trace was written or none is pending: d1 is then dL/dv)
//     dW += g,  dalpha += g v,  dq += dr v,  g <- w + a v (the efficacy, for dX; only when w is given; then also
//     dc0 += dyc0 (w + a v) and dc1 likewise, the carried rows' gradients, when they are given)
//     second update:  gx2 = total where its clamp was inactive;  dq1 += ep1 gx2;  sums gx2 . q1, gx2 . v1;
//                     gx1 = keep gx2                                              (else gx1 = total)
//     first update:   gx1 <- gx1 where its clamp was inactive;  dq0 += ep0 gx1;  sums gx1 . q0, gx1 . e0;
//                     d0 = keep gx1 (+ d1 when the trace was not written: d1 is then dL/de0, the input passed on)
//     none pending:   d0 = total
//
// d1 and q may be null (read as zero); dq is null with q; w is null when dX is not needed; c is read only when
// carried, and c.dc0 and c.dc1 are null when the rows need no gradient.
template <typename T>
struct CarriedRows {
  const T* c0;
  const T* c1;
  T dy0, dy1;  // this row's dL/dYc
  T* dc0;
  T* dc1;
};

template <typename T, int pending, bool write, bool first, bool carried>
inline PendingSums<T> deferred_grad_row(T* __restrict g, const T* __restrict e0, const PendingRow<T>& u, T keep, T lo,
                                        T hi, const T* __restrict w, const T* __restrict a, const T* __restrict d1,
                                        const T* __restrict q, T dr, const CarriedRows<T>& c, T* __restrict d0,
                                        T* __restrict dw, T* __restrict da, T* __restrict dq, T* __restrict dq0,
                                        T* __restrict dq1, int64_t n) {
  using sb3_spikeplastic_fast::load;
  using sb3_spikeplastic_fast::splat;
  using sb3_spikeplastic_fast::store;
  using V = typename sb3_spikeplastic_fast::Lanes<T>::V;
  using Mask = typename sb3_spikeplastic_fast::Lanes<T>::Mask;
  constexpr int64_t L = sb3_spikeplastic_fast::Lanes<T>::n;
  constexpr bool d1_of_v = write || pending == 0;
  const V keep_v = splat(keep), ep0_v = splat(u.ep0), ep1_v = splat(u.ep1), lo_v = splat(lo), hi_v = splat(hi),
          dr_v = splat(dr), dy0_v = splat(c.dy0), dy1_v = splat(c.dy1);
  V s_ep0 = splat<T>(0), s_keep0 = splat<T>(0), s_ep1 = splat<T>(0), s_keep1 = splat<T>(0);
  int64_t i = 0;
  for (; i + L <= n; i += L) {
    const V e = load(e0 + i), av = load(a + i);
    V gv = load(g + i);
    if constexpr (carried) gv = gv + dy0_v * load(c.c0 + i) + dy1_v * load(c.c1 + i);
    V v1 = e, v = e;
    Mask clip1 = {}, clip2 = {};
    if constexpr (pending >= 1) {
      const V x = e * keep_v + ep0_v * load(u.q0 + i);
      clip1 = (x < lo_v) | (x > hi_v);
      v = v1 = clamp_lanes(x, lo_v, hi_v);
    }
    if constexpr (pending == 2) {
      const V x = v1 * keep_v + ep1_v * load(u.q1 + i);
      clip2 = (x < lo_v) | (x > hi_v);
      v = clamp_lanes(x, lo_v, hi_v);
    }
    V total = av * gv;
    if (d1_of_v && d1 != nullptr) total = load(d1 + i) + total;
    if (q != nullptr) {
      total = total + dr_v * load(q + i);
      store(dq + i, load(dq + i) + dr_v * v);
    }
    if constexpr (first) {
      store(dw + i, gv);
      store(da + i, gv * v);
    } else {
      store(dw + i, load(dw + i) + gv);
      store(da + i, load(da + i) + gv * v);
    }
    if (w != nullptr) {
      const V ev = load(w + i) + av * v;
      store(g + i, ev);
      if (carried && c.dc0 != nullptr) {
        store(c.dc0 + i, load(c.dc0 + i) + dy0_v * ev);
        store(c.dc1 + i, load(c.dc1 + i) + dy1_v * ev);
      }
    }
    if constexpr (pending == 0) {
      store(d0 + i, total);
    } else {
      V gx1 = total;
      if constexpr (pending == 2) {
        const V gx2 = (V)((Mask)total & ~clip2);
        store(dq1 + i, load(dq1 + i) + ep1_v * gx2);
        s_ep1 += gx2 * load(u.q1 + i);
        s_keep1 += gx2 * v1;
        gx1 = keep_v * gx2;
      }
      gx1 = (V)((Mask)gx1 & ~clip1);
      store(dq0 + i, load(dq0 + i) + ep0_v * gx1);
      s_ep0 += gx1 * load(u.q0 + i);
      s_keep0 += gx1 * e;
      V out = keep_v * gx1;
      if (!d1_of_v && d1 != nullptr) out = load(d1 + i) + out;
      store(d0 + i, out);
    }
  }
  PendingSums<T> sums;
  if constexpr (pending >= 1) {
    sums.ep0 = sb3_spikeplastic_fast::sum_lanes<T>(s_ep0);
    sums.keep0 = sb3_spikeplastic_fast::sum_lanes<T>(s_keep0);
  }
  if constexpr (pending == 2) {
    sums.ep1 = sb3_spikeplastic_fast::sum_lanes<T>(s_ep1);
    sums.keep1 = sb3_spikeplastic_fast::sum_lanes<T>(s_keep1);
  }
  for (; i < n; ++i) {
    const T e = e0[i];
    T gi = g[i];
    if constexpr (carried) gi = gi + c.dy0 * c.c0[i] + c.dy1 * c.c1[i];
    T v1 = e, v = e;
    bool clip1 = false, clip2 = false;
    if constexpr (pending >= 1) {
      const T x = e * keep + u.ep0 * u.q0[i];
      clip1 = x < lo || x > hi;
      v = v1 = std::min(hi, std::max(lo, x));
    }
    if constexpr (pending == 2) {
      const T x = v1 * keep + u.ep1 * u.q1[i];
      clip2 = x < lo || x > hi;
      v = std::min(hi, std::max(lo, x));
    }
    T total = a[i] * gi;
    if (d1_of_v && d1 != nullptr) total = d1[i] + total;
    if (q != nullptr) {
      total = total + dr * q[i];
      dq[i] += dr * v;
    }
    if constexpr (first) {
      dw[i] = gi;
      da[i] = gi * v;
    } else {
      dw[i] += gi;
      da[i] += gi * v;
    }
    if (w != nullptr) {
      g[i] = w[i] + a[i] * v;
      if (carried && c.dc0 != nullptr) {
        c.dc0[i] += c.dy0 * g[i];
        c.dc1[i] += c.dy1 * g[i];
      }
    }
    if constexpr (pending == 0) {
      d0[i] = total;
    } else {
      T gx1 = total;
      if constexpr (pending == 2) {
        const T gx2 = clip2 ? T(0) : total;
        dq1[i] += u.ep1 * gx2;
        sums.ep1 += gx2 * u.q1[i];
        sums.keep1 += gx2 * v1;
        gx1 = keep * gx2;
      }
      gx1 = clip1 ? T(0) : gx1;
      dq0[i] += u.ep0 * gx1;
      sums.ep0 += gx1 * u.q0[i];
      sums.keep0 += gx1 * e;
      T out = keep * gx1;
      if (!d1_of_v && d1 != nullptr) out = d1[i] + out;
      d0[i] = out;
    }
  }
  return sums;
}
}  // namespace

namespace sb3_spikeplastic_fast {

// The product without a trace update: the deferred form with none pending and no Oja row sums. -> (Y, Yc (empty
// without carried rows C))
std::tuple<at::Tensor, at::Tensor> plastic_linear_forward(const at::Tensor& X, const at::Tensor& W,
                                                          const at::Tensor& alpha, const at::Tensor& E,
                                                          const at::Tensor& C) {
  const at::Tensor none;
  const DeferredProduct out =
      plastic_linear_deferred_forward(X, W, alpha, E, C, none, none, none, none, none, 0, 1, false);
  return std::make_tuple(out.Y, out.Yc);
}

// dX and dC are empty unless need_x_grad (dC also without C); dE starts from dE_init when it is given.
ProductGradients plastic_linear_backward(const at::Tensor& grad, const at::Tensor& grad_c, const at::Tensor& X,
                                         const at::Tensor& W, const at::Tensor& alpha, const at::Tensor& E,
                                         const at::Tensor& C, bool need_x_grad, const at::Tensor& dE_init) {
  const at::Tensor none;
  const DeferredProductGradients g = plastic_linear_deferred_backward(
      grad, grad_c, X, W, alpha, E, C, none, none, none, none, none, dE_init, none, need_x_grad, 0, 1, false);
  return {g.dX, g.dW, g.dalpha, g.dE, g.dC};
}

namespace {

// The pending updates given: none, (p0, q0), or (p0, q0) then (p1, q1); contiguous copies.
struct Pending {
  at::Tensor p0, q0, p1, q1;
  int64_t count;
};

Pending pending_updates(const at::Tensor& p0, const at::Tensor& q0, const at::Tensor& p1, const at::Tensor& q1) {
  TORCH_CHECK(p0.defined() == q0.defined() && p1.defined() == q1.defined() && (p0.defined() || !p1.defined()),
              "plastic_linear_deferred: each pending update is a pair (p, q), and a second needs a first");
  auto contiguous = [](const at::Tensor& t) { return t.defined() ? t.contiguous() : at::Tensor(); };
  return {contiguous(p0), contiguous(q0), contiguous(p1), contiguous(q1),
          static_cast<int64_t>(p0.defined()) + static_cast<int64_t>(p1.defined())};
}

template <typename scalar_t>
PendingRow<scalar_t> pending_row(const DeferredOperands<scalar_t>& v, int64_t b, int64_t o, int64_t O, int64_t I) {
  PendingRow<scalar_t> u{nullptr, 0, nullptr, 0};
  if (v.p0 != nullptr) u = {v.q0 + b * I, v.eta * v.p0[b * O + o], nullptr, 0};
  if (v.p1 != nullptr) u.q1 = v.q1 + b * I, u.ep1 = v.eta * v.p1[b * O + o];
  return u;
}

// Carried rows C (B, 2, n_in), contiguous; undefined when none are given.
at::Tensor carried_rows(const at::Tensor& C, const at::Tensor& X) {
  if (!C.defined()) return C;
  TORCH_CHECK(C.dim() == 3 && C.size(0) == X.size(0) && C.size(1) == 2 && C.size(2) == X.size(2) &&
                  C.scalar_type() == X.scalar_type(),
              "plastic_linear: carried rows (B, 2, n_in) of X's dtype");
  return C.contiguous();
}

}  // namespace

// The deferred trace update (srm_interval.cpp): the trace this interval's product uses is E_t, the input trace E with
// the pending updates of the previous intervals applied, clamp(keep E + (eta p0) (x) q0, +-e_max) and then likewise
// (p1, q1), built in the same pass over E as the efficacy (which also takes the Oja term's row sums r = E_t q when q
// is given, and the carried rows' products Yc = C eff^T when C is), so that each interval reads its trace once:
//
//     forward:   E_t = the pending updates applied to E[b],  eff = W + alpha * E_t,  r = E_t q[b],  Y[b] = X[b] eff^T
//
// E_t is written out only when write (a sequence keeps every other trace: an interval that leaves its two
// predecessors' updates pending recomputes the trace in registers, forward and backward, instead of storing it).
// keep = 1 - eta and eta p are computed as trace_step.cpp computes them. Y, Yc, E_t and r are each empty where not
// computed.
DeferredProduct plastic_linear_deferred_forward(
    const at::Tensor& X_in, const at::Tensor& W_in, const at::Tensor& alpha_in, const at::Tensor& E_in,
    const at::Tensor& C_in, const at::Tensor& p0_in, const at::Tensor& q0_in, const at::Tensor& p1_in,
    const at::Tensor& q1_in, const at::Tensor& q_in, double eta, double e_max, bool write) {
  check_operands(X_in, W_in, alpha_in, E_in);
  const Pending u = pending_updates(p0_in, q0_in, p1_in, q1_in);
  write = write && u.count > 0;
  const at::Tensor X = X_in.contiguous(), W = W_in.contiguous(), alpha = alpha_in.contiguous(), E = E_in.contiguous();
  const at::Tensor q = q_in.defined() ? q_in.contiguous() : at::Tensor(), C = carried_rows(C_in, X);
  const int64_t B = X.size(0), O = W.size(0), I = W.size(1), N = W.numel();
  const at::Tensor none = at::empty({0}, E.options());
  at::Tensor Y = at::empty({B, X.size(1), O}, X.options());
  at::Tensor Yc = C.defined() ? at::empty({B, 2, O}, X.options()) : none;
  at::Tensor Et = write ? at::empty_like(E, at::MemoryFormat::Contiguous) : none;
  at::Tensor r = q.defined() ? at::empty({B, O}, E.options()) : none;
  const int64_t nb = block_size(B, N), blocks = (B + nb - 1) / nb;
  AT_DISPATCH_FLOATING_TYPES(E.scalar_type(), "plastic_linear_deferred_forward", [&] {
    const DeferredOperands<scalar_t> v = deferred_operands<scalar_t>(W, alpha, E, u.p0, u.q0, u.p1, u.q1, q, eta,
                                                                     e_max);
    scalar_t* et_p = write ? Et.data_ptr<scalar_t>() : nullptr;
    scalar_t* r_p = q.defined() ? r.data_ptr<scalar_t>() : nullptr;
    const scalar_t* c_p = C.defined() ? C.data_ptr<scalar_t>() : nullptr;
    scalar_t* yc_p = C.defined() ? Yc.data_ptr<scalar_t>() : nullptr;
    const bool blas = has_blas<scalar_t>();
    const CallerDenormalMode mode;
    at::parallel_for(0, blocks, 1, [&](int64_t begin, int64_t end) {
      const DenormalModeScope denormals(mode);
      at::NoGradGuard no_grad;
      at::Tensor buf = at::empty({nb, O, I}, W.options());
      scalar_t* buf_p = buf.data_ptr<scalar_t>();
      for (int64_t block = begin; block < end; ++block) {
        const int64_t b0 = block * nb, n = std::min(nb, B - b0);
        for (int64_t b = b0; b < b0 + n; ++b) {
          const scalar_t* q_b = v.q != nullptr ? v.q + b * I : nullptr;
          const scalar_t* c0 = c_p != nullptr ? c_p + 2 * b * I : nullptr;
          const scalar_t* c1 = c_p != nullptr ? c0 + I : nullptr;
          with_pending(u.count, write, [&](auto count, auto written) {
            auto rows = [&](auto carries) {
              for (int64_t o = 0; o < O; ++o) {
                const int64_t off = b * N + o * I;
                const RowSums<scalar_t> sums =
                    deferred_row<scalar_t, decltype(count)::value, decltype(written)::value, decltype(carries)::value>(
                        v.e + off, pending_row(v, b, o, O, I), v.keep, v.lo, v.hi, v.w + o * I, v.a + o * I, q_b, c0,
                        c1, et_p != nullptr ? et_p + off : nullptr, buf_p + (b - b0) * N + o * I, I);
                if (r_p != nullptr) r_p[b * O + o] = sums.q;
                if constexpr (decltype(carries)::value) {
                  yc_p[2 * b * O + o] = sums.c0;
                  yc_p[(2 * b + 1) * O + o] = sums.c1;
                }
              }
            };
            c0 != nullptr ? rows(std::true_type{}) : rows(std::false_type{});
          });
        }
        if (!spike_block_forward<scalar_t>(X, Y, buf_p, b0, n)) block_forward<scalar_t>(blas, X, Y, buf, b0, n);
      }
    });
  });
  DeferredProduct out;
  out.Y = Y;
  out.Yc = Yc;
  out.E_t = Et;
  out.r = r;
  return out;
}

// The backward pass of plastic_linear_deferred_forward, one pass over E per environment (deferred_grad_row): grad_c
// is dL/dYc (undefined: zero), dE1 the gradient of the trace the interval passes on (may be undefined): of E_t when
// it was written, else of E itself; dr is dL/dr (undefined without q). dX is empty unless need_x_grad, dq without q,
// dp_k and dq_k where the pending update k is not given, deta without a pending update, dC unless need_x_grad and C
// is given. fill_grad, when given,
// writes grad's rows of environments [b0, b0 + n) and is called just before they are multiplied (by the thread that
// multiplies them), so that they are read from cache rather than from wherever a pass over the whole batch left them.
DeferredProductGradients plastic_linear_deferred_backward(
    const at::Tensor& grad_in, const at::Tensor& grad_c_in, const at::Tensor& X_in, const at::Tensor& W_in,
    const at::Tensor& alpha_in, const at::Tensor& E_in, const at::Tensor& C_in, const at::Tensor& p0_in,
    const at::Tensor& q0_in, const at::Tensor& p1_in, const at::Tensor& q1_in, const at::Tensor& q_in,
    const at::Tensor& dE1_in, const at::Tensor& dr_in, bool need_x_grad, double eta, double e_max, bool write,
    const std::function<void(int64_t, int64_t)>& fill_grad) {
  check_operands(X_in, W_in, alpha_in, E_in);
  TORCH_CHECK(!fill_grad || grad_in.is_contiguous(), "plastic_linear: a gradient filled per environment is contiguous");
  const Pending u = pending_updates(p0_in, q0_in, p1_in, q1_in);
  write = write && u.count > 0;
  const at::Tensor g = grad_in.contiguous(), X = X_in.contiguous(), W = W_in.contiguous(),
                   alpha = alpha_in.contiguous(), E = E_in.contiguous();
  const at::Tensor q = q_in.defined() ? q_in.contiguous() : at::Tensor(), C = carried_rows(C_in, X);
  const at::Tensor gc = C.defined() && grad_c_in.defined() ? grad_c_in.contiguous() : at::Tensor();
  const at::Tensor dE1 = dE1_in.defined() ? dE1_in.contiguous() : at::Tensor();
  const at::Tensor dr = q.defined() && dr_in.defined() ? dr_in.contiguous() : at::Tensor();
  TORCH_CHECK(!dE1.defined() || (dE1.sizes() == E.sizes() && dE1.scalar_type() == E.scalar_type()),
              "plastic_linear: the gradient of E does not match E");
  const int64_t B = X.size(0), O = W.size(0), I = W.size(1), N = W.numel();
  TORCH_CHECK(g.dim() == 3 && g.size(0) == B && g.size(1) == X.size(1) && g.size(2) == O &&
                  g.scalar_type() == E.scalar_type(),
              "plastic_linear: the gradient does not match Y (B, L, o)");
  TORCH_CHECK(!gc.defined() || (gc.dim() == 3 && gc.size(0) == B && gc.size(1) == 2 && gc.size(2) == O),
              "plastic_linear: the gradient of the carried rows' products does not match Yc (B, 2, o)");
  const at::Tensor none = at::empty({0}, E.options());
  at::Tensor dE0 = at::empty_like(E, at::MemoryFormat::Contiguous);
  const int64_t threads = at::get_num_threads();
  at::Tensor acc = at::empty({threads, 2, O, I}, W.options());
  std::vector<char> used(threads, 0);
  at::Tensor dX = need_x_grad ? at::empty_like(X, at::MemoryFormat::Contiguous) : none;
  at::Tensor dC = need_x_grad && C.defined() ? at::zeros({B, 2, I}, E.options()) : none;
  at::Tensor dq = q.defined() ? at::zeros({B, I}, E.options()) : none;
  at::Tensor dq0 = u.count >= 1 ? at::zeros({B, I}, E.options()) : none;
  at::Tensor dp0 = u.count >= 1 ? at::empty({B, O}, E.options()) : none;
  at::Tensor dq1 = u.count == 2 ? at::zeros({B, I}, E.options()) : none;
  at::Tensor dp1 = u.count == 2 ? at::empty({B, O}, E.options()) : none;
  at::Tensor deta_rows = at::zeros({B}, E.options().dtype(at::kDouble));
  const int64_t nb = block_size(B, N);
  AT_DISPATCH_FLOATING_TYPES(E.scalar_type(), "plastic_linear_deferred_backward", [&] {
    const DeferredOperands<scalar_t> v = deferred_operands<scalar_t>(W, alpha, E, u.p0, u.q0, u.p1, u.q1, q, eta,
                                                                     e_max);
    auto ptr = [](at::Tensor& t) { return t.numel() > 0 ? t.data_ptr<scalar_t>() : nullptr; };
    const scalar_t* d1_p = dE1.defined() ? dE1.data_ptr<scalar_t>() : nullptr;
    const scalar_t* dr_p = dr.defined() ? dr.data_ptr<scalar_t>() : nullptr;
    const scalar_t* c_p = C.defined() ? C.data_ptr<scalar_t>() : nullptr;
    const scalar_t* gc_p = gc.defined() ? gc.data_ptr<scalar_t>() : nullptr;
    scalar_t *d0_p = dE0.data_ptr<scalar_t>(), *dq_p = ptr(dq), *dq0_p = ptr(dq0), *dp0_p = ptr(dp0),
             *dq1_p = ptr(dq1), *dp1_p = ptr(dp1), *dc_p = ptr(dC);
    double* deta_p = deta_rows.data_ptr<double>();
    const bool blas = has_blas<scalar_t>();
    backward_blocks<scalar_t>(B, nb, W, acc, used, [&](int64_t b0, int64_t n, at::Tensor& G, scalar_t* dw_t,
                                                        scalar_t* da_t, bool& first) {
      if (fill_grad) fill_grad(b0, n);
      if (!spike_block_gradient<scalar_t>(g, X, G, b0, n)) block_gradient<scalar_t>(blas, g, X, G, b0, n);
      scalar_t* G_p = G.data_ptr<scalar_t>();
      for (int64_t b = b0; b < b0 + n; ++b) {
        const scalar_t* q_b = v.q != nullptr ? v.q + b * I : nullptr;
        scalar_t* dq_b = dq_p != nullptr ? dq_p + b * I : nullptr;
        scalar_t* dq0_b = dq0_p != nullptr ? dq0_p + b * I : nullptr;
        scalar_t* dq1_b = dq1_p != nullptr ? dq1_p + b * I : nullptr;
        // with carried rows but no gradient for their products, G has no part of theirs to add
        const scalar_t* c0 = c_p != nullptr && gc_p != nullptr ? c_p + 2 * b * I : nullptr;
        scalar_t* dc0 = dc_p != nullptr && gc_p != nullptr ? dc_p + 2 * b * I : nullptr;
        double deta = 0;
        with_pending(u.count, write, [&](auto count, auto written) {
          constexpr int pending = decltype(count)::value;
          constexpr bool wrote = decltype(written)::value;
          auto rows = [&](auto carries) {
            constexpr bool with_c = decltype(carries)::value;
            for (int64_t o = 0; o < O; ++o) {
              const int64_t off = b * N + o * I;
              const PendingRow<scalar_t> row = pending_row(v, b, o, O, I);
              const CarriedRows<scalar_t> carried{
                  c0, c0 != nullptr ? c0 + I : nullptr, c0 != nullptr ? gc_p[2 * b * O + o] : scalar_t(0),
                  c0 != nullptr ? gc_p[(2 * b + 1) * O + o] : scalar_t(0), dc0, dc0 != nullptr ? dc0 + I : nullptr};
              scalar_t* G_row = G_p + (b - b0) * N + o * I;
              const scalar_t* d1 = d1_p != nullptr ? d1_p + off : nullptr;
              const scalar_t dr_o = dr_p != nullptr ? dr_p[b * O + o] : scalar_t(0);
              const scalar_t* w_row = need_x_grad ? v.w + o * I : nullptr;
              const PendingSums<scalar_t> sums =
                  first ? deferred_grad_row<scalar_t, pending, wrote, true, with_c>(
                              G_row, v.e + off, row, v.keep, v.lo, v.hi, w_row, v.a + o * I, d1, q_b, dr_o, carried,
                              d0_p + off, dw_t + o * I, da_t + o * I, dq_b, dq0_b, dq1_b, I)
                        : deferred_grad_row<scalar_t, pending, wrote, false, with_c>(
                              G_row, v.e + off, row, v.keep, v.lo, v.hi, w_row, v.a + o * I, d1, q_b, dr_o, carried,
                              d0_p + off, dw_t + o * I, da_t + o * I, dq_b, dq0_b, dq1_b, I);
              // ep_k = eta p_k, keep = 1 - eta: dL/dp_k = eta (gx_k . q_k),
              // dL/deta = sum_k p_k (gx_k . q_k) - gx_k . v_k
              if constexpr (pending >= 1) {
                dp0_p[b * O + o] = v.eta * sums.ep0;
                deta += static_cast<double>(v.p0[b * O + o] * sums.ep0 - sums.keep0);
              }
              if constexpr (pending == 2) {
                dp1_p[b * O + o] = v.eta * sums.ep1;
                deta += static_cast<double>(v.p1[b * O + o] * sums.ep1 - sums.keep1);
              }
            }
          };
          c0 != nullptr ? rows(std::true_type{}) : rows(std::false_type{});
        });
        first = false;  // the rows of a thread's first environment fill its sums
        deta_p[b] = deta;
      }
      if (need_x_grad) block_input_gradient<scalar_t>(blas, g, G, dX, b0, n);  // G holds the efficacy
    });
  });
  const at::Tensor sums = thread_sums(acc, used);
  const at::Tensor d_eta = u.count > 0 ? deta_rows.sum().to(E.scalar_type()) : none;
  DeferredProductGradients out;
  out.dX = dX;
  out.dW = sums.select(0, 0);
  out.dalpha = sums.select(0, 1);
  out.dE = dE0;
  out.dq = dq;
  out.dp0 = dp0;
  out.dq0 = dq0;
  out.dp1 = dp1;
  out.dq1 = dq1;
  out.deta = d_eta;
  out.dC = dC;
  return out;
}

// The spike products' density limit: sets it to limit when limit >= 0 and returns the previous one (0 disables
// them); and the counts of environments' products (spike, dense) since the library was loaded.
double set_spike_density_limit(double limit) {
  TORCH_CHECK(limit <= 1, "spike_density_limit: a fraction of X's values in [0, 1], got ", limit);
  return limit < 0 ? spike_density_limit.load() : spike_density_limit.exchange(limit);
}

std::vector<int64_t> spike_product_counts() { return {spike_products.load(), dense_products.load()}; }

}  // namespace sb3_spikeplastic_fast

TORCH_LIBRARY_FRAGMENT(sb3_spikeplastic_fast, m) {
  m.def("spike_density_limit(float limit) -> float", &sb3_spikeplastic_fast::set_spike_density_limit);
  m.def("spike_product_counts() -> int[]", &sb3_spikeplastic_fast::spike_product_counts);
  m.def(
      "plastic_linear_forward(Tensor X, Tensor W, Tensor alpha, Tensor E, Tensor? carried) "
      "-> (Tensor Y, Tensor Y_carried)");
  // the gradient of each input, named as it
  m.def(
      "plastic_linear_backward(Tensor grad, Tensor? grad_carried, Tensor X, Tensor W, Tensor alpha, Tensor E, "
      "Tensor? carried, bool need_x_grad) -> (Tensor X, Tensor W, Tensor alpha, Tensor E, Tensor carried)");
}

namespace {

at::Tensor given_or_none(const std::optional<at::Tensor>& t) { return t.has_value() ? *t : at::Tensor(); }

std::tuple<at::Tensor, at::Tensor> plastic_linear_forward_op(const at::Tensor& X, const at::Tensor& W,
                                                             const at::Tensor& alpha, const at::Tensor& E,
                                                             const std::optional<at::Tensor>& C) {
  return sb3_spikeplastic_fast::plastic_linear_forward(X, W, alpha, E, given_or_none(C));
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> plastic_linear_backward_op(
    const at::Tensor& grad, const std::optional<at::Tensor>& grad_c, const at::Tensor& X, const at::Tensor& W,
    const at::Tensor& alpha, const at::Tensor& E, const std::optional<at::Tensor>& C, bool need_x_grad) {
  const sb3_spikeplastic_fast::ProductGradients g = sb3_spikeplastic_fast::plastic_linear_backward(
      grad, given_or_none(grad_c), X, W, alpha, E, given_or_none(C), need_x_grad, at::Tensor());
  return std::make_tuple(g.dX, g.dW, g.dalpha, g.dE, g.dC);
}

}  // namespace

TORCH_LIBRARY_IMPL(sb3_spikeplastic_fast, CPU, m) {
  m.impl("plastic_linear_forward", &plastic_linear_forward_op);
  m.impl("plastic_linear_backward", &plastic_linear_backward_op);
}
