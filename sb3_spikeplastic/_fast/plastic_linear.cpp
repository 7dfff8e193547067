// The plastic layer's synaptic product (CPU fast path of sb3_spikeplastic.layers.PlasticSRMLayer.project):
//
//     Y[b] = X[b] (W + alpha * E[b])^T          X (B, R, n_in), W, alpha (n_out, n_in), E (B, n_out, n_in)
//
// Eager PyTorch materialises the per-environment efficacy W_eff (B, n_out, n_in) for a batched matmul, and in
// the backward its gradient dW_eff of the same size, then reads both again for dW, dalpha and dE: four extra
// passes over trace-sized arrays. Here one environment's W_eff[b] (or its gradient) is built one row at a time
// (or in one (n_out, n_in) buffer) that stays in cache:
//
//     forward:   eff = W + alpha * E[b];          Y[b] = X[b] eff^T
//     backward:  G = dY[b]^T X[b]                 (the gradient of W_eff[b], in W's layout)
//                dE[b] = alpha * G,   dW += G,   dalpha += E[b] * G       (one pass over G and E[b])
//                dX[b] = dY[b] (W + alpha * E[b])                         (only when X needs a gradient)
//
// Environments are independent, so they are split between threads (dW and dalpha are summed per thread, then
// added). The rows of X are mostly binary spikes: a row with at most `max_density * n_in` nonzeros is kept as
// a list of its nonzeros, and its products touch only those columns (the forward pass adds up the rows of the
// transposed efficacy of its nonzeros; the backward pass scatters into G). An environment whose rows are all
// dense uses dense matrix products instead.
//
// Equal to the eager ops to float rounding (sums run in another order).

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/grad_mode.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/mm.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <c10/core/ScalarType.h>
#include <torch/library.h>

#include "denormal_mode.h"

#include <algorithm>
#include <cstdint>
#include <tuple>
#include <vector>

namespace {

void check_operands(const at::Tensor& X, const at::Tensor& W, const at::Tensor& alpha, const at::Tensor& E) {
  TORCH_CHECK(X.dim() == 3 && W.dim() == 2 && E.dim() == 3 && W.sizes() == alpha.sizes() && E.size(0) == X.size(0) &&
                  E.size(1) == W.size(0) && E.size(2) == W.size(1) && X.size(2) == W.size(1),
              "plastic_linear: X (B, L, i), W and alpha (o, i), E (B, o, i)");
  const auto dtype = E.scalar_type();
  TORCH_CHECK((dtype == at::kFloat || dtype == at::kDouble) && X.scalar_type() == dtype && W.scalar_type() == dtype &&
                  alpha.scalar_type() == dtype,
              "plastic_linear: float32 or float64 tensors of one dtype");
}

// Environments per task: enough work per task (~64k multiply-adds) that a thread's start-up does not dominate.
int64_t batch_grain(int64_t rows, int64_t n_out, int64_t n_in) {
  return std::max<int64_t>(1, 65536 / std::max<int64_t>(1, rows * n_out * n_in / 4));
}

// The nonzeros of one environment's rows: row r is sparse when it has at most max_nnz nonzeros; its columns and
// values are idx/val[start[r] .. start[r + 1]). A dense row has start[r] == start[r + 1] and dense[r] = 1.
template <typename scalar_t>
struct RowNonzeros {
  std::vector<int32_t> idx;
  std::vector<scalar_t> val;
  std::vector<int64_t> start;
  std::vector<char> dense;
  int64_t n_sparse = 0;

  void build(const scalar_t* x, int64_t R, int64_t I, int64_t max_nnz) {
    // Branch-free: every column is written and the count advances on nonzeros (spikes are unpredictable); a row
    // stops at max_nnz + 1 nonzeros, which marks it dense.
    idx.resize(R * (max_nnz + 1) + 1);
    val.resize(idx.size());
    start.assign(R + 1, 0);
    dense.assign(R, 0);
    n_sparse = 0;
    int64_t n = 0;
    for (int64_t r = 0; r < R; ++r) {
      const scalar_t* row = x + r * I;
      const int64_t first = n, limit = first + max_nnz;
      int64_t i = 0;
      for (; i < I && n <= limit; ++i) {
        idx[n] = static_cast<int32_t>(i);
        val[n] = row[i];
        n += row[i] != scalar_t(0);
      }
      if (n > limit) {
        n = first;
        dense[r] = 1;
      } else {
        ++n_sparse;
      }
      start[r + 1] = n;
    }
  }
};

template <typename scalar_t>
inline void efficacy_into(const scalar_t* __restrict w, const scalar_t* __restrict a, const scalar_t* __restrict e,
                          scalar_t* __restrict out, int64_t n) {
#pragma omp simd
  for (int64_t k = 0; k < n; ++k) out[k] = w[k] + a[k] * e[k];
}

// effT (n_in, n_out) = (W + alpha * E_b)^T, in blocks of 16 columns so that the written rows stay in L1.
template <typename scalar_t>
void efficacy_transposed(const scalar_t* __restrict w, const scalar_t* __restrict a, const scalar_t* __restrict e,
                         scalar_t* __restrict effT, int64_t O, int64_t I) {
  constexpr int64_t block = 16;
  for (int64_t i0 = 0; i0 < I; i0 += block) {
    const int64_t n = std::min(block, I - i0);
    for (int64_t o = 0; o < O; ++o) {
      const int64_t off = o * I + i0;
      for (int64_t k = 0; k < n; ++k) effT[(i0 + k) * O + o] = w[off + k] + a[off + k] * e[off + k];
    }
  }
}

template <typename scalar_t>
inline scalar_t dot(const scalar_t* __restrict x, const scalar_t* __restrict y, int64_t n) {
  scalar_t s = 0;
#pragma omp simd reduction(+ : s)
  for (int64_t i = 0; i < n; ++i) s += x[i] * y[i];
  return s;
}

template <typename scalar_t>
inline scalar_t gather_dot(const int32_t* __restrict idx, const scalar_t* __restrict val,
                           const scalar_t* __restrict y, int64_t n) {
  scalar_t s = 0;
#pragma omp simd reduction(+ : s)
  for (int64_t k = 0; k < n; ++k) s += val[k] * y[idx[k]];
  return s;
}

template <typename scalar_t>
inline void axpy(scalar_t* __restrict y, scalar_t g, const scalar_t* __restrict x, int64_t n) {
#pragma omp simd
  for (int64_t i = 0; i < n; ++i) y[i] += g * x[i];
}

template <typename scalar_t>
inline void scatter_axpy(scalar_t* __restrict y, scalar_t g, const int32_t* __restrict idx,
                         const scalar_t* __restrict val, int64_t n) {
  for (int64_t k = 0; k < n; ++k) y[idx[k]] += g * val[k];
}

// One row of the efficacy's gradient g: dE = g * alpha, and the batch sums dW += g, dalpha += g * E.
template <typename scalar_t>
inline void efficacy_grad_row(const scalar_t* __restrict g, const scalar_t* __restrict e,
                              const scalar_t* __restrict a, scalar_t* __restrict de, scalar_t* __restrict dw,
                              scalar_t* __restrict da, int64_t n) {
#pragma omp simd
  for (int64_t i = 0; i < n; ++i) {
    de[i] = g[i] * a[i];
    dw[i] += g[i];
    da[i] += g[i] * e[i];
  }
}

at::Tensor plastic_linear_forward(const at::Tensor& X_in, const at::Tensor& W_in, const at::Tensor& alpha_in,
                                  const at::Tensor& E_in, double max_density) {
  check_operands(X_in, W_in, alpha_in, E_in);
  const at::Tensor X = X_in.contiguous(), W = W_in.contiguous(), alpha = alpha_in.contiguous(), E = E_in.contiguous();
  const int64_t B = X.size(0), R = X.size(1), O = W.size(0), I = W.size(1), N = W.numel();
  // max_density 0: every row dense (a row of zeros too)
  const int64_t max_nnz = max_density > 0 ? static_cast<int64_t>(max_density * static_cast<double>(I)) : -1;
  at::Tensor Y = at::empty({B, R, O}, X.options());
  AT_DISPATCH_FLOATING_TYPES(E.scalar_type(), "plastic_linear_forward", [&] {
    const scalar_t *x_p = X.data_ptr<scalar_t>(), *w_p = W.data_ptr<scalar_t>(), *a_p = alpha.data_ptr<scalar_t>(),
                   *e_p = E.data_ptr<scalar_t>();
    scalar_t* y_p = Y.data_ptr<scalar_t>();
    const CallerDenormalMode mode;
    at::parallel_for(0, B, batch_grain(R, O, I), [&](int64_t begin, int64_t end) {
      const DenormalModeScope denormals(mode);
      at::NoGradGuard no_grad;  // grad mode is per thread: the pool's threads would record the products below
      RowNonzeros<scalar_t> nz;
      std::vector<scalar_t> eff;
      at::Tensor buf;
      for (int64_t b = begin; b < end; ++b) {
        const scalar_t *x_b = x_p + b * R * I, *e_b = e_p + b * N;
        scalar_t* y_b = y_p + b * R * O;
        nz.build(x_b, R, I, max_nnz);
        if (nz.n_sparse == 0) {  // all rows dense: one matrix product with the whole efficacy
          if (!buf.defined()) buf = at::empty({O, I}, W.options());
          efficacy_into<scalar_t>(w_p, a_p, e_b, buf.data_ptr<scalar_t>(), N);
          at::Tensor y = Y.select(0, b);
          at::mm_out(y, X.select(0, b), buf.t());
          continue;
        }
        // Sparse rows add up the efficacy's columns of their nonzeros: rows of effT, contiguous over n_out.
        eff.resize(I * O);
        efficacy_transposed<scalar_t>(w_p, a_p, e_b, eff.data(), O, I);
        for (int64_t r = 0; r < R; ++r) {
          scalar_t* y_r = y_b + r * O;
          std::fill(y_r, y_r + O, scalar_t(0));
          if (nz.dense[r]) {
            const scalar_t* x_r = x_b + r * I;
            for (int64_t i = 0; i < I; ++i) axpy<scalar_t>(y_r, x_r[i], eff.data() + i * O, O);
          } else {
            for (int64_t k = nz.start[r]; k < nz.start[r + 1]; ++k)
              axpy<scalar_t>(y_r, nz.val[k], eff.data() + static_cast<int64_t>(nz.idx[k]) * O, O);
          }
        }
      }
    });
  });
  return Y;
}

// Returns (dX, dW, dalpha, dE); dX is empty unless need_x_grad.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> plastic_linear_backward(
    const at::Tensor& grad_in, const at::Tensor& X_in, const at::Tensor& W_in, const at::Tensor& alpha_in,
    const at::Tensor& E_in, bool need_x_grad, double max_density) {
  check_operands(X_in, W_in, alpha_in, E_in);
  const at::Tensor g = grad_in.contiguous(), X = X_in.contiguous(), W = W_in.contiguous(),
                   alpha = alpha_in.contiguous(), E = E_in.contiguous();
  const int64_t B = X.size(0), R = X.size(1), O = W.size(0), I = W.size(1), N = W.numel();
  TORCH_CHECK(g.dim() == 3 && g.size(0) == B && g.size(1) == R && g.size(2) == O &&
                  g.scalar_type() == E.scalar_type(),
              "plastic_linear: the gradient does not match Y (B, L, o)");
  // max_density 0: every row dense (a row of zeros too)
  const int64_t max_nnz = max_density > 0 ? static_cast<int64_t>(max_density * static_cast<double>(I)) : -1;
  const int64_t threads = at::get_num_threads();
  at::Tensor dE = at::empty_like(E, at::MemoryFormat::Contiguous);
  // Per-thread sums of dW and dalpha (summed over threads at the end).
  at::Tensor acc = at::zeros({threads, 2, O, I}, W.options());
  at::Tensor dX = need_x_grad ? at::zeros_like(X, at::MemoryFormat::Contiguous) : at::empty({0}, X.options());
  AT_DISPATCH_FLOATING_TYPES(E.scalar_type(), "plastic_linear_backward", [&] {
    const scalar_t *x_p = X.data_ptr<scalar_t>(), *w_p = W.data_ptr<scalar_t>(), *a_p = alpha.data_ptr<scalar_t>(),
                   *e_p = E.data_ptr<scalar_t>(), *g_p = g.data_ptr<scalar_t>();
    scalar_t *de_p = dE.data_ptr<scalar_t>(), *acc_p = acc.data_ptr<scalar_t>();
    scalar_t* dx_p = need_x_grad ? dX.data_ptr<scalar_t>() : nullptr;
    const CallerDenormalMode mode;
    at::parallel_for(0, B, batch_grain(R, O, I), [&](int64_t begin, int64_t end) {
      const DenormalModeScope denormals(mode);
      at::NoGradGuard no_grad;
      scalar_t* dw_t = acc_p + at::get_thread_num() * 2 * N;
      scalar_t* da_t = dw_t + N;
      RowNonzeros<scalar_t> nz;
      std::vector<scalar_t> grow, eff;
      at::Tensor G, buf;
      for (int64_t b = begin; b < end; ++b) {
        const scalar_t *x_b = x_p + b * R * I, *e_b = e_p + b * N, *g_b = g_p + b * R * O;
        scalar_t* de_b = de_p + b * N;
        nz.build(x_b, R, I, max_nnz);
        if (nz.n_sparse == 0) {  // all rows dense: matrix products with the whole efficacy and its gradient
          if (!G.defined()) {
            G = at::empty({O, I}, W.options());
            buf = at::empty({O, I}, W.options());
          }
          const at::Tensor gy = g.select(0, b);
          at::mm_out(G, gy.t(), X.select(0, b));
          const scalar_t* G_p = G.data_ptr<scalar_t>();
          for (int64_t o = 0; o < O; ++o) {
            const int64_t off = o * I;
            efficacy_grad_row<scalar_t>(G_p + off, e_b + off, a_p + off, de_b + off, dw_t + off, da_t + off, I);
          }
          if (need_x_grad) {
            efficacy_into<scalar_t>(w_p, a_p, e_b, buf.data_ptr<scalar_t>(), N);
            at::Tensor dx = dX.select(0, b);
            at::mm_out(dx, gy, buf);
          }
          continue;
        }
        grow.assign(I, scalar_t(0));
        if (need_x_grad) eff.resize(I);
        for (int64_t o = 0; o < O; ++o) {
          const int64_t off = o * I;
          std::fill(grow.begin(), grow.end(), scalar_t(0));
          for (int64_t r = 0; r < R; ++r) {
            const scalar_t gy = g_b[r * O + o];
            if (gy == scalar_t(0)) continue;
            const int64_t s = nz.start[r];
            if (nz.dense[r]) {
              axpy<scalar_t>(grow.data(), gy, x_b + r * I, I);
            } else {
              scatter_axpy<scalar_t>(grow.data(), gy, nz.idx.data() + s, nz.val.data() + s, nz.start[r + 1] - s);
            }
          }
          efficacy_grad_row<scalar_t>(grow.data(), e_b + off, a_p + off, de_b + off, dw_t + off, da_t + off, I);
          if (need_x_grad) {
            efficacy_into<scalar_t>(w_p + off, a_p + off, e_b + off, eff.data(), I);
            scalar_t* dx_b = dx_p + b * R * I;
            for (int64_t r = 0; r < R; ++r) axpy<scalar_t>(dx_b + r * I, g_b[r * O + o], eff.data(), I);
          }
        }
      }
    });
  });
  at::Tensor sums = acc.sum(0);
  return std::make_tuple(dX, sums.select(0, 0), sums.select(0, 1), dE);
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(sb3_spikeplastic_fast, m) {
  m.def("plastic_linear_forward(Tensor X, Tensor W, Tensor alpha, Tensor E, float max_density) -> Tensor");
  m.def(
      "plastic_linear_backward(Tensor grad, Tensor X, Tensor W, Tensor alpha, Tensor E, bool need_x_grad, "
      "float max_density) -> (Tensor, Tensor, Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(sb3_spikeplastic_fast, CPU, m) {
  m.impl("plastic_linear_forward", &plastic_linear_forward);
  m.impl("plastic_linear_backward", &plastic_linear_backward);
}
