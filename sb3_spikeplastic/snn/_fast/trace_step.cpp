// Fused Hebbian trace update (the CPU fast path of sb3_spikeplastic.plasticity.hebbian_trace_step).
//
// Every built-in rule updates its trace as
//
//     p  = post - (oja ? E q : 0)                     (B, n_out)   the Oja forms subtract E's prediction
//     x  = E * (1 - eta) + (eta * p) (x) q            (B, n_out, n_in)
//     E' = clamp(x, -e_max, e_max)
//
// In eager PyTorch this is ~7 passes over trace-sized arrays forward and ~13 backward (each op reads and writes
// the whole trace, and autograd keeps x). Here each (batch, row) of the trace is read once forward and E, dE'
// once backward; the row (n_in values) stays in L1 between the two inner loops that need it.
//
// Backward, per row (b, o), with g = dL/dE' and the clip mask recomputed exactly as in the forward pass:
//
//     gx_i   = g_i * [-e_max <= x_i <= e_max]
//     gp     = eta * sum_i gx_i q_i                    dL/dpost[b, o]
//     dE_i   = (1 - eta) gx_i - (oja ? gp q_i : 0)
//     dq_i  += eta gx_i p - (oja ? gp E_i : 0)         (accumulated over o: rows of one b are one task)
//     deta  += sum_i gx_i (p q_i - E_i)
//
// Results agree with the eager ops to float rounding (the summation order of the row sums differs), not
// bitwise.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros_like.h>
#include <c10/core/ScalarType.h>
#include <torch/library.h>

#include "denormal_mode.h"
#include "kernels.h"
#include "lanes.h"

#include <algorithm>
#include <tuple>
#include <utility>

namespace {

void check_inputs(const at::Tensor& E, const at::Tensor& post, const at::Tensor& pre) {
  TORCH_CHECK(E.dim() == 3 && post.dim() == 2 && pre.dim() == 2, "trace_step: E (B, o, i), post (B, o), pre (B, i)");
  TORCH_CHECK(post.size(0) == E.size(0) && post.size(1) == E.size(1) && pre.size(0) == E.size(0) &&
                  pre.size(1) == E.size(2),
              "trace_step: shapes of E, post and pre do not agree");
  TORCH_CHECK(E.scalar_type() == at::kFloat || E.scalar_type() == at::kDouble, "trace_step: float32 or float64 only");
  TORCH_CHECK(post.scalar_type() == E.scalar_type() && pre.scalar_type() == E.scalar_type(),
              "trace_step: dtypes must agree");
  TORCH_CHECK(E.device().is_cpu() && post.device().is_cpu() && pre.device().is_cpu(), "trace_step: CPU tensors only");
}

// Row kernels are plain functions (a #pragma cannot stand inside AT_DISPATCH's macro argument); their row sums
// use lanes.h's register of partial sums.
using sb3_spikeplastic_fast::dot;
using sb3_spikeplastic_fast::Lanes;
using sb3_spikeplastic_fast::load;
using sb3_spikeplastic_fast::splat;
using sb3_spikeplastic_fast::store;
using sb3_spikeplastic_fast::sum_lanes;

// One trace row (b, o) forward: y = clamp(e * keep + (eta p) q); returns p.
template <typename scalar_t>
scalar_t forward_row(const scalar_t* __restrict e, const scalar_t* __restrict q, scalar_t* __restrict y, int64_t n,
                     scalar_t post, scalar_t eta, scalar_t keep, scalar_t lo, scalar_t hi, bool oja) {
  const scalar_t p = post - (oja ? dot(e, q, n) : scalar_t(0));
  const scalar_t ep = eta * p;
#pragma omp simd
  for (int64_t i = 0; i < n; ++i) {
    const scalar_t x = e[i] * keep + ep * q[i];
    y[i] = x < lo ? lo : (x > hi ? hi : x);
  }
  return p;
}

// One trace row (b, o) backward (see the top of the file): writes de, adds to dq, returns (dL/dpost, the row's
// contribution to dL/deta).
template <typename scalar_t>
std::pair<scalar_t, scalar_t> backward_row(const scalar_t* __restrict g, const scalar_t* __restrict e,
                                           const scalar_t* __restrict q, scalar_t* __restrict de,
                                           scalar_t* __restrict dq, int64_t n, scalar_t p, scalar_t eta,
                                           scalar_t keep, scalar_t lo, scalar_t hi, bool oja) {
  const scalar_t ep = eta * p;
  // pass 1: the masked gradient (kept in de) and the two row sums
  using V = typename Lanes<scalar_t>::V;
  using Mask = typename Lanes<scalar_t>::Mask;
  constexpr int64_t W = Lanes<scalar_t>::n;
  const V keep_v = splat(keep), ep_v = splat(ep), p_v = splat(p), lo_v = splat(lo), hi_v = splat(hi);
  V acc_q = splat<scalar_t>(0), acc_diff = splat<scalar_t>(0);
  int64_t i = 0;
  for (; i + W <= n; i += W) {
    const V e_i = load(e + i), q_i = load(q + i);
    const V x = e_i * keep_v + ep_v * q_i;
    const V v = (V)((Mask)load(g + i) & ~((x < lo_v) | (x > hi_v)));  // 0 where the clamp was active
    store(de + i, v);
    acc_q += v * q_i;
    acc_diff += v * (p_v * q_i - e_i);
  }
  scalar_t gq = sum_lanes<scalar_t>(acc_q), gdiff = sum_lanes<scalar_t>(acc_diff);
  for (; i < n; ++i) {
    const scalar_t x = e[i] * keep + ep * q[i];
    const scalar_t v = (x < lo || x > hi) ? scalar_t(0) : g[i];
    de[i] = v;
    gq += v * q[i];
    gdiff += v * (p * q[i] - e[i]);
  }
  const scalar_t gp = eta * gq;
  // pass 2 (the row is in L1): the Oja forms also reach E and q through p = post - E q
  const scalar_t gp_oja = oja ? gp : scalar_t(0);
#pragma omp simd
  for (int64_t k = 0; k < n; ++k) {
    const scalar_t v = de[k];
    de[k] = keep * v - gp_oja * q[k];
    dq[k] += ep * v - gp_oja * e[k];
  }
  return {gp, gdiff};
}

}  // namespace

namespace sb3_spikeplastic_fast {

// Returns (E', p); p is kept for the backward pass.
std::tuple<at::Tensor, at::Tensor> trace_step_forward(const at::Tensor& E_in, const at::Tensor& post_in,
                                                     const at::Tensor& pre_in, double eta, double e_max, bool oja) {
  check_inputs(E_in, post_in, pre_in);
  const at::Tensor E = E_in.contiguous(), post = post_in.contiguous(), pre = pre_in.contiguous();
  const int64_t B = E.size(0), O = E.size(1), I = E.size(2);
  at::Tensor out = at::empty_like(E, at::MemoryFormat::Contiguous);
  at::Tensor p_out = at::empty_like(post, at::MemoryFormat::Contiguous);
  AT_DISPATCH_FLOATING_TYPES(E.scalar_type(), "trace_step_forward", [&] {
    const scalar_t eta_s = static_cast<scalar_t>(eta), keep = scalar_t(1) - eta_s;
    const scalar_t hi = static_cast<scalar_t>(e_max), lo = -hi;
    const scalar_t *e_p = E.data_ptr<scalar_t>(), *post_p = post.data_ptr<scalar_t>(), *q_p = pre.data_ptr<scalar_t>();
    scalar_t *o_p = out.data_ptr<scalar_t>(), *pp = p_out.data_ptr<scalar_t>();
    const CallerDenormalMode mode;
    at::parallel_for(0, B * O, std::max<int64_t>(1, 16384 / std::max<int64_t>(I, 1)), [&](int64_t begin, int64_t end) {
      const DenormalModeScope denormals(mode);
      for (int64_t r = begin; r < end; ++r) {
        pp[r] = forward_row<scalar_t>(e_p + r * I, q_p + (r / O) * I, o_p + r * I, I, post_p[r], eta_s, keep, lo, hi,
                                      oja);
      }
    });
  });
  return std::make_tuple(out, p_out);
}

// Returns (dE, dpost, dpre, deta).
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> trace_step_backward(
    const at::Tensor& grad_in, const at::Tensor& E_in, const at::Tensor& p_in, const at::Tensor& pre_in, double eta,
    double e_max, bool oja) {
  check_inputs(E_in, p_in, pre_in);
  const at::Tensor g = grad_in.contiguous(), E = E_in.contiguous(), p = p_in.contiguous(), pre = pre_in.contiguous();
  TORCH_CHECK(g.sizes() == E.sizes() && g.scalar_type() == E.scalar_type(), "trace_step: grad does not match E");
  const int64_t B = E.size(0), O = E.size(1), I = E.size(2);
  at::Tensor dE = at::empty_like(E, at::MemoryFormat::Contiguous);
  at::Tensor dpost = at::empty_like(p, at::MemoryFormat::Contiguous);
  at::Tensor dpre = at::zeros_like(pre, at::MemoryFormat::Contiguous);
  at::Tensor deta_rows = at::empty({B}, E.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(E.scalar_type(), "trace_step_backward", [&] {
    const scalar_t eta_s = static_cast<scalar_t>(eta), keep = scalar_t(1) - eta_s;
    const scalar_t hi = static_cast<scalar_t>(e_max), lo = -hi;
    const scalar_t *g_p = g.data_ptr<scalar_t>(), *e_p = E.data_ptr<scalar_t>(), *p_p = p.data_ptr<scalar_t>(),
                   *q_p = pre.data_ptr<scalar_t>();
    scalar_t *de_p = dE.data_ptr<scalar_t>(), *dpost_p = dpost.data_ptr<scalar_t>(), *dq_p = dpre.data_ptr<scalar_t>();
    double* deta_p = deta_rows.data_ptr<double>();
    // One task per batch row: dq[b] is accumulated over that row's n_out trace rows without races.
    const CallerDenormalMode mode;
    at::parallel_for(0, B, 1, [&](int64_t begin, int64_t end) {
      const DenormalModeScope denormals(mode);
      for (int64_t b = begin; b < end; ++b) {
        double deta = 0;
        for (int64_t o = 0; o < O; ++o) {
          const int64_t r = b * O + o;
          const auto [gp, gdiff] = backward_row<scalar_t>(g_p + r * I, e_p + r * I, q_p + b * I, de_p + r * I,
                                                          dq_p + b * I, I, p_p[r], eta_s, keep, lo, hi, oja);
          dpost_p[r] = gp;
          deta += static_cast<double>(gdiff);
        }
        deta_p[b] = deta;
      }
    });
  });
  return std::make_tuple(dE, dpost, dpre, deta_rows.sum().to(E.scalar_type()));
}

}  // namespace sb3_spikeplastic_fast

TORCH_LIBRARY_FRAGMENT(sb3_spikeplastic_fast, m) {
  m.def(
      "trace_step_forward(Tensor E, Tensor post, Tensor pre, float eta, float e_max, bool oja) "
      "-> (Tensor trace, Tensor p)");
  // the gradients of trace_step_forward's inputs, named as them
  m.def(
      "trace_step_backward(Tensor grad, Tensor E, Tensor p, Tensor pre, float eta, float e_max, bool oja) "
      "-> (Tensor E, Tensor post, Tensor pre, Tensor eta)");
}

TORCH_LIBRARY_IMPL(sb3_spikeplastic_fast, CPU, m) {
  m.impl("trace_step_forward", &sb3_spikeplastic_fast::trace_step_forward);
  m.impl("trace_step_backward", &sb3_spikeplastic_fast::trace_step_backward);
}
