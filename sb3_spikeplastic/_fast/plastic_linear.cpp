// The plastic layer's synaptic product (CPU fast path of sb3_spikeplastic.layers.PlasticSRMLayer.project):
//
//     Y[b] = X[b] (W + alpha * E[b])^T          X (B, R, n_in), W, alpha (n_out, n_in), E (B, n_out, n_in)
//
// Eager PyTorch materialises the per-environment efficacy W_eff (B, n_out, n_in) for a batched matmul, and in
// the backward its gradient dW_eff of the same size, then reads both again for dW, dalpha and dE: four extra
// passes over trace-sized arrays. Here the efficacy (or its gradient) of a block of a few environments is built
// in a buffer that stays in cache (at most ~256 KB), used by one batched matrix product and overwritten by the next
// block's; a block, not one environment, because each at::bmm_out call costs microseconds of dispatch, which at
// the CPU entry's sizes (16 environments, 12 x 170 x 64) was most of the layer's time. Where a block holds one
// environment (the paper network's 600 x 64 layers), its products call BLAS directly instead (gemm below):
//
//     forward:   eff = W + alpha * E[b];          Y[b] = X[b] eff^T
//     backward:  G = dY[b]^T X[b]                 (the gradient of W_eff[b], in W's layout)
//                dE[b] = alpha * G (+ dE_init[b]),  dW += G,  dalpha += E[b] * G    (one pass over G and E[b],
//                                                         which also writes the efficacy over G when dX is needed)
//                dX[b] = dY[b] (W + alpha * E[b])                         (only when X needs a gradient)
//
// Environments are independent, so they are split between threads (dW and dalpha are summed per thread, then
// added; a thread's first row fills its sums, so they are not zero-filled first). The products stay dense: X's rows are binary spikes, but skipping the silent inputs (gathering the
// efficacy's columns of the firing ones) needs the efficacy transposed per environment, which costs more than it
// saves at these sizes (benchmarks/README.md, "Sparse products").
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

#include <algorithm>
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

template <typename scalar_t>
inline void efficacy_into(const scalar_t* __restrict w, const scalar_t* __restrict a, const scalar_t* __restrict e,
                          scalar_t* __restrict out, int64_t n) {
#pragma omp simd
  for (int64_t k = 0; k < n; ++k) out[k] = w[k] + a[k] * e[k];
}

// One row of the efficacy's gradient g: dE = g * alpha (+ de0, another gradient of E, when given), and the batch
// sums dW += g, dalpha += g * E (or, for a thread's first row, dW = g, dalpha = g * E: its sums start unfilled).
// With w given, g's row is then overwritten with the efficacy's row w + alpha * E, which the input's gradient
// needs next: E's row is read once for both.
template <typename scalar_t, bool first>
inline void efficacy_grad_row(scalar_t* __restrict g, const scalar_t* __restrict e, const scalar_t* __restrict a,
                              const scalar_t* __restrict w, const scalar_t* __restrict de0, scalar_t* __restrict de,
                              scalar_t* __restrict dw, scalar_t* __restrict da, int64_t n) {
  if (de0 != nullptr) {
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) de[i] = de0[i] + g[i] * a[i];
  } else {
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) de[i] = g[i] * a[i];
  }
  if constexpr (first) {
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) {
      dw[i] = g[i];
      da[i] = g[i] * e[i];
    }
  } else {
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) {
      dw[i] += g[i];
      da[i] += g[i] * e[i];
    }
  }
  if (w != nullptr) {
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) g[i] = w[i] + a[i] * e[i];
  }
}

}  // namespace

namespace sb3_spikeplastic_fast {

at::Tensor plastic_linear_forward(const at::Tensor& X_in, const at::Tensor& W_in, const at::Tensor& alpha_in,
                                  const at::Tensor& E_in) {
  check_operands(X_in, W_in, alpha_in, E_in);
  const at::Tensor X = X_in.contiguous(), W = W_in.contiguous(), alpha = alpha_in.contiguous(), E = E_in.contiguous();
  const int64_t B = X.size(0), R = X.size(1), O = W.size(0), I = W.size(1), N = W.numel();
  at::Tensor Y = at::empty({B, R, O}, X.options());
  const int64_t nb = block_size(B, N), blocks = (B + nb - 1) / nb;
  AT_DISPATCH_FLOATING_TYPES(E.scalar_type(), "plastic_linear_forward", [&] {
    const scalar_t *w_p = W.data_ptr<scalar_t>(), *a_p = alpha.data_ptr<scalar_t>(), *e_p = E.data_ptr<scalar_t>();
    const scalar_t* x_p = X.data_ptr<scalar_t>();
    scalar_t* y_p = Y.data_ptr<scalar_t>();
    const bool blas = has_blas<scalar_t>();
    const CallerDenormalMode mode;
    at::parallel_for(0, blocks, 1, [&](int64_t begin, int64_t end) {
      const DenormalModeScope denormals(mode);
      at::NoGradGuard no_grad;  // grad mode is per thread: the pool's threads would record the products below
      at::Tensor buf = at::empty({nb, O, I}, W.options());
      scalar_t* buf_p = buf.data_ptr<scalar_t>();
      for (int64_t block = begin; block < end; ++block) {
        const int64_t b0 = block * nb, n = std::min(nb, B - b0);
        for (int64_t b = 0; b < n; ++b) efficacy_into<scalar_t>(w_p, a_p, e_p + (b0 + b) * N, buf_p + b * N, N);
        if (blas && n == 1) {  // Y[b0] (R, O) = X[b0] (R, I) eff^T
          gemm<scalar_t>('T', 'N', O, R, I, buf_p, I, x_p + b0 * R * I, I, y_p + b0 * R * O, O);
        } else {
          at::Tensor y = Y.narrow(0, b0, n);
          at::bmm_out(y, X.narrow(0, b0, n), buf.narrow(0, 0, n).transpose(1, 2));
        }
      }
    });
  });
  return Y;
}

// Returns (dX, dW, dalpha, dE); dX is empty unless need_x_grad.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> plastic_linear_backward(
    const at::Tensor& grad_in, const at::Tensor& X_in, const at::Tensor& W_in, const at::Tensor& alpha_in,
    const at::Tensor& E_in, bool need_x_grad, const at::Tensor& dE_init_in) {
  check_operands(X_in, W_in, alpha_in, E_in);
  const at::Tensor dE_init = dE_init_in.defined() ? dE_init_in.contiguous() : at::Tensor();
  TORCH_CHECK(!dE_init.defined() || (dE_init.sizes() == E_in.sizes() && dE_init.scalar_type() == E_in.scalar_type()),
              "plastic_linear: dE_init does not match E");
  const at::Tensor g = grad_in.contiguous(), X = X_in.contiguous(), W = W_in.contiguous(),
                   alpha = alpha_in.contiguous(), E = E_in.contiguous();
  const int64_t B = X.size(0), R = X.size(1), O = W.size(0), I = W.size(1), N = W.numel();
  TORCH_CHECK(g.dim() == 3 && g.size(0) == B && g.size(1) == R && g.size(2) == O &&
                  g.scalar_type() == E.scalar_type(),
              "plastic_linear: the gradient does not match Y (B, L, o)");
  at::Tensor dE = at::empty_like(E, at::MemoryFormat::Contiguous);
  // Per-thread sums of dW and dalpha, added up at the end; a thread's first row fills its sums (no zero-fill).
  const int64_t threads = at::get_num_threads();
  at::Tensor acc = at::empty({threads, 2, O, I}, W.options());
  std::vector<char> used(threads, 0);
  at::Tensor dX = need_x_grad ? at::empty_like(X, at::MemoryFormat::Contiguous) : at::empty({0}, X.options());
  const int64_t nb = block_size(B, N), blocks = (B + nb - 1) / nb;
  AT_DISPATCH_FLOATING_TYPES(E.scalar_type(), "plastic_linear_backward", [&] {
    const scalar_t *w_p = W.data_ptr<scalar_t>(), *a_p = alpha.data_ptr<scalar_t>(), *e_p = E.data_ptr<scalar_t>();
    scalar_t *de_p = dE.data_ptr<scalar_t>(), *acc_p = acc.data_ptr<scalar_t>();
    const scalar_t *x_p = X.data_ptr<scalar_t>(), *g_p = g.data_ptr<scalar_t>();
    scalar_t* dx_p = need_x_grad ? dX.data_ptr<scalar_t>() : nullptr;
    const bool blas = has_blas<scalar_t>();
    const scalar_t* de0_p = dE_init.defined() ? dE_init.data_ptr<scalar_t>() : nullptr;
    const CallerDenormalMode mode;
    at::parallel_for(0, blocks, 1, [&](int64_t begin, int64_t end) {
      const DenormalModeScope denormals(mode);
      at::NoGradGuard no_grad;
      const int64_t tid = at::get_thread_num();
      scalar_t* dw_t = acc_p + tid * 2 * N;
      scalar_t* da_t = dw_t + N;
      bool first = used[tid] == 0;
      used[tid] = 1;
      at::Tensor G = at::empty({nb, O, I}, W.options());
      scalar_t* G_p = G.data_ptr<scalar_t>();
      for (int64_t block = begin; block < end; ++block) {
        const int64_t b0 = block * nb, n = std::min(nb, B - b0);
        if (blas && n == 1) {  // G (O, I) = dY[b0]^T (O, R) X[b0] (R, I)
          gemm<scalar_t>('N', 'T', I, O, R, x_p + b0 * R * I, I, g_p + b0 * R * O, O, G_p, I);
        } else {
          at::Tensor G_n = G.narrow(0, 0, n);
          at::bmm_out(G_n, g.narrow(0, b0, n).transpose(1, 2), X.narrow(0, b0, n));
        }
        // G is consumed row by row; with need_x_grad its buffer then holds the block's efficacy.
        for (int64_t b = 0; b < n; ++b) {
          const scalar_t* e_b = e_p + (b0 + b) * N;
          scalar_t* de_b = de_p + (b0 + b) * N;
          scalar_t* G_b = G_p + b * N;
          const scalar_t* de0_b = de0_p != nullptr ? de0_p + (b0 + b) * N : nullptr;
          for (int64_t o = 0; o < O; ++o) {
            const int64_t off = o * I;
            const scalar_t* de0_row = de0_b != nullptr ? de0_b + off : nullptr;
            const scalar_t* w_row = need_x_grad ? w_p + off : nullptr;
            if (first) {
              efficacy_grad_row<scalar_t, true>(G_b + off, e_b + off, a_p + off, w_row, de0_row, de_b + off,
                                                dw_t + off, da_t + off, I);
            } else {
              efficacy_grad_row<scalar_t, false>(G_b + off, e_b + off, a_p + off, w_row, de0_row, de_b + off,
                                                 dw_t + off, da_t + off, I);
            }
          }
          first = false;
        }
        if (need_x_grad) {
          if (blas && n == 1) {  // dX[b0] (R, I) = dY[b0] (R, O) eff (O, I)
            gemm<scalar_t>('N', 'N', I, R, O, G_p, I, g_p + b0 * R * O, O, dx_p + b0 * R * I, I);
          } else {
            at::Tensor dx = dX.narrow(0, b0, n);
            at::bmm_out(dx, g.narrow(0, b0, n), G.narrow(0, 0, n));
          }
        }
      }
    });
  });
  at::Tensor sums;
  for (int64_t t = 0; t < threads; ++t) {
    if (!used[t]) continue;
    if (!sums.defined()) {
      sums = acc.select(0, t);
    } else {
      sums.add_(acc.select(0, t));
    }
  }
  if (!sums.defined()) sums = at::zeros({2, O, I}, W.options());  // an empty batch
  return std::make_tuple(dX, sums.select(0, 0), sums.select(0, 1), dE);
}

}  // namespace sb3_spikeplastic_fast

TORCH_LIBRARY_FRAGMENT(sb3_spikeplastic_fast, m) {
  m.def("plastic_linear_forward(Tensor X, Tensor W, Tensor alpha, Tensor E) -> Tensor");
  m.def(
      "plastic_linear_backward(Tensor grad, Tensor X, Tensor W, Tensor alpha, Tensor E, bool need_x_grad) "
      "-> (Tensor, Tensor, Tensor, Tensor)");
}

namespace {

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> plastic_linear_backward_op(
    const at::Tensor& grad, const at::Tensor& X, const at::Tensor& W, const at::Tensor& alpha, const at::Tensor& E,
    bool need_x_grad) {
  return sb3_spikeplastic_fast::plastic_linear_backward(grad, X, W, alpha, E, need_x_grad);
}

}  // namespace

TORCH_LIBRARY_IMPL(sb3_spikeplastic_fast, CPU, m) {
  m.impl("plastic_linear_forward", &sb3_spikeplastic_fast::plastic_linear_forward);
  m.impl("plastic_linear_backward", &plastic_linear_backward_op);
}
