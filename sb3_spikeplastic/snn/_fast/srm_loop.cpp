// Compiled SRM threshold/refractory recursion (the CPU fast path of sb3_spikeplastic.neurons.srm_spike_loop).
//
// Per neuron and step t, in the tensor's dtype and in exactly this order (the eager reference in neurons.py
// performs the same IEEE operations as separate tensor ops):
//
//     h2 = (h2 + h1) * d
//     u  = syn[t] - (h2 * kappa)
//     s  = (u >= theta) ? 1 : 0
//     h1 = (h1 * d) + s
//
// d, kappa and theta arrive as doubles and are rounded to the tensor dtype first, as PyTorch does with a
// Python-float scalar operand. The file must be compiled with -ffp-contract=off and without -ffast-math so
// that no multiply-add is fused and no operation is reordered: the results are then bit-identical to the
// eager loop, whatever the vector width the compiler picks for the inner loop.
//
// Loop order: rows of the batch are independent (parallelised with at::parallel_for); within a row, time is
// the sequential outer loop and the n neurons of one step (contiguous in memory) the inner, vectorisable loop.

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

#include "srm_loop_checks.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <tuple>

namespace {

// GCC if-converts (and so vectorises) the comparisons below only when floating-point operations may be assumed
// not to trap; the results do not change (no reassociation, no contraction).
#if defined(__GNUC__) && !defined(__clang__)
#define SB3SP_VECTORISE_SELECTS __attribute__((optimize("no-trapping-math")))
#else
#define SB3SP_VECTORISE_SELECTS
#endif

// exp(x) for x <= 0 in float32, written so that the compiler vectorises it (glibc's expf does not vectorise
// without -ffast-math): x = n ln2 + r with |r| <= ln2 / 2 (Cody-Waite: ln2 in two parts, so that n ln2 is exact),
// exp(r) by its Taylor polynomial of degree 7 (truncation < 1e-8 relative), 2^n by the exponent bits. Within
// 2 ulp of exp; 0 below -87.3, where exp leaves float32's normal range.
SB3SP_VECTORISE_SELECTS inline float exp_nonpositive(float x) {
  const float clamped = x < -87.3f ? -87.3f : x;
  const float n = __builtin_floorf(clamped * 1.44269504088896341f + 0.5f);
  const float r = (clamped - n * 0.693145751953125f) - n * 1.42860682030941723212e-6f;
  float poly = 1.f / 5040.f;
  poly = poly * r + 1.f / 720.f;
  poly = poly * r + 1.f / 120.f;
  poly = poly * r + 1.f / 24.f;
  poly = poly * r + 1.f / 6.f;
  poly = poly * r + 0.5f;
  poly = poly * r + 1.f;
  poly = poly * r + 1.f;
  const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
  float two_n;
  std::memcpy(&two_n, &bits, sizeof two_n);
  const float y = poly * two_n;
  return x < -87.3f ? 0.f : y;
}

// SLAYER's surrogate gradient of one step's membrane, scale_w * exp(|u - theta| / neg_width): the ops of
// neurons.slayer_surrogate in their order, up to the exponential (within 2 ulp of torch.exp in float32).
SB3SP_VECTORISE_SELECTS void surrogate_row(const float* __restrict u, float* __restrict g, int64_t n, float theta,
                                           float neg_width, float scale_w) {
  for (int64_t j = 0; j < n; ++j) g[j] = exp_nonpositive(__builtin_fabsf(u[j] - theta) / neg_width) * scale_w;
}

void surrogate_row(const double* __restrict u, double* __restrict g, int64_t n, double theta, double neg_width,
                   double scale_w) {
  for (int64_t j = 0; j < n; ++j) g[j] = std::exp(std::abs(u[j] - theta) / neg_width) * scale_w;
}

// Per neuron and step, in this order (see the top of the file), and each neuron's spike rate over the interval
// (rate starts at zero); with kSurrogate also the surrogate gradient of each step's membrane while it is in L1,
// instead of in five passes over the whole membrane afterwards.
template <typename scalar_t, bool kSurrogate>
void srm_rows(const scalar_t* __restrict syn, scalar_t* __restrict h1, scalar_t* __restrict h2,
              scalar_t* __restrict spikes, scalar_t* __restrict membrane, scalar_t* __restrict surrogate,
              scalar_t* __restrict rate, int64_t length, int64_t n, scalar_t d, scalar_t kappa, scalar_t theta,
              scalar_t neg_width, scalar_t scale_w) {
  const scalar_t one = scalar_t(1);
  const scalar_t zero = scalar_t(0);
  for (int64_t t = 0; t < length; ++t) {
    const scalar_t* __restrict x = syn + t * n;
    scalar_t* __restrict u_out = membrane + t * n;
    scalar_t* __restrict s_out = spikes + t * n;
    for (int64_t j = 0; j < n; ++j) {
      const scalar_t a1 = h1[j];
      const scalar_t a2 = (h2[j] + a1) * d;
      const scalar_t r = a2 * kappa;
      const scalar_t u = x[j] - r;
      const scalar_t s = (u >= theta) ? one : zero;
      const scalar_t b1 = a1 * d;
      h2[j] = a2;
      h1[j] = b1 + s;
      u_out[j] = u;
      s_out[j] = s;
      rate[j] += s;  // a count of 0/1 values: exact in any order
    }
    if constexpr (kSurrogate) surrogate_row(u_out, surrogate + t * n, n, theta, neg_width, scale_w);
  }
  // spikes.mean(1) as ATen computes it: the (exact) sum divided by the length
  const scalar_t steps = static_cast<scalar_t>(length);
  for (int64_t j = 0; j < n; ++j) rate[j] = rate[j] / steps;
}

// The loop over the batch's rows; surrogate is undefined unless the surrogate is wanted.
void run_srm_loop(const at::Tensor& syn, at::Tensor& spikes, at::Tensor& membrane, at::Tensor& h1, at::Tensor& h2,
                  const at::Tensor& surrogate, at::Tensor& rate, double d, double kappa, double theta, double width,
                  double scale) {
  const int64_t batch = syn.size(0), length = syn.size(1), n = syn.size(2);
  const int64_t row = length * n;
  // about 32k element-steps per task, the ATen default grain
  const int64_t grain = row > 0 ? std::max<int64_t>(1, 32768 / row) : batch;
  AT_DISPATCH_FLOATING_TYPES(syn.scalar_type(), "srm_loop_cpu", [&] {
    const scalar_t d_s = static_cast<scalar_t>(d);
    const scalar_t kappa_s = static_cast<scalar_t>(kappa);
    const scalar_t theta_s = static_cast<scalar_t>(theta);
    // as PyTorch rounds the Python-float operands of div_(-width) and mul_(scale / width)
    const scalar_t neg_width = static_cast<scalar_t>(-width);
    const scalar_t scale_w = static_cast<scalar_t>(scale / width);
    const scalar_t* syn_p = syn.data_ptr<scalar_t>();
    scalar_t* h1_p = h1.data_ptr<scalar_t>();
    scalar_t* h2_p = h2.data_ptr<scalar_t>();
    scalar_t* s_p = spikes.data_ptr<scalar_t>();
    scalar_t* u_p = membrane.data_ptr<scalar_t>();
    scalar_t* g_p = surrogate.defined() ? surrogate.data_ptr<scalar_t>() : nullptr;
    scalar_t* r_p = rate.data_ptr<scalar_t>();
    const CallerDenormalMode mode;
    at::parallel_for(0, batch, grain, [&](int64_t begin, int64_t end) {
      const DenormalModeScope denormals(mode);
      for (int64_t b = begin; b < end; ++b) {
        if (g_p != nullptr) {
          srm_rows<scalar_t, true>(syn_p + b * row, h1_p + b * n, h2_p + b * n, s_p + b * row, u_p + b * row,
                                   g_p + b * row, r_p + b * n, length, n, d_s, kappa_s, theta_s, neg_width,
                                   scale_w);
        } else {
          srm_rows<scalar_t, false>(syn_p + b * row, h1_p + b * n, h2_p + b * n, s_p + b * row, u_p + b * row,
                                    nullptr, r_p + b * n, length, n, d_s, kappa_s, theta_s, neg_width, scale_w);
        }
      }
    });
  });
}

}  // namespace

namespace sb3_spikeplastic_fast {

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> srm_loop_interval_cpu(
    const at::Tensor& synaptic, const at::Tensor& h1, const at::Tensor& h2, double d, double kappa, double theta,
    double width, double scale, bool need_surrogate) {
  check_srm_operands(synaptic, h1, h2);
  TORCH_CHECK(synaptic.device().is_cpu() && h1.device().is_cpu() && h2.device().is_cpu(),
              "srm_loop: CPU tensors only");
  const at::Tensor syn = synaptic.contiguous();
  at::Tensor spikes = at::empty_like(syn, at::MemoryFormat::Contiguous);
  at::Tensor membrane = at::empty_like(syn, at::MemoryFormat::Contiguous);
  at::Tensor new_h1 = h1.clone(at::MemoryFormat::Contiguous);
  at::Tensor new_h2 = h2.clone(at::MemoryFormat::Contiguous);
  at::Tensor rate = at::zeros_like(new_h1);
  const at::Tensor surrogate = need_surrogate ? at::empty_like(syn, at::MemoryFormat::Contiguous) : at::Tensor();
  run_srm_loop(syn, spikes, membrane, new_h1, new_h2, surrogate, rate, d, kappa, theta, width, scale);
  return std::make_tuple(spikes, membrane, new_h1, new_h2,
                         need_surrogate ? surrogate : at::empty({0}, syn.options()), rate);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> srm_loop_cpu(const at::Tensor& synaptic,
                                                                      const at::Tensor& h1, const at::Tensor& h2,
                                                                      double d, double kappa, double theta) {
  auto [spikes, membrane, new_h1, new_h2, surrogate, rate] =
      srm_loop_interval_cpu(synaptic, h1, h2, d, kappa, theta, 1.0, 1.0, false);
  return std::make_tuple(spikes, membrane, new_h1, new_h2);
}

}  // namespace sb3_spikeplastic_fast

TORCH_LIBRARY(sb3_spikeplastic_fast, m) {
  m.def(
      "srm_loop(Tensor synaptic, Tensor h1, Tensor h2, float d, float kappa, float theta) "
      "-> (Tensor spikes, Tensor membrane, Tensor h1, Tensor h2)");
}

TORCH_LIBRARY_IMPL(sb3_spikeplastic_fast, CPU, m) {
  m.impl("srm_loop", &sb3_spikeplastic_fast::srm_loop_cpu);
}
