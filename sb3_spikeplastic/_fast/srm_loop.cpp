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
#include <ATen/ops/empty_like.h>
#include <c10/core/ScalarType.h>
#include <torch/library.h>

#include "denormal_mode.h"
#include "kernels.h"

#include "srm_loop_checks.h"

#include <algorithm>
#include <cstdint>
#include <tuple>

namespace {

template <typename scalar_t>
void srm_rows(const scalar_t* __restrict syn, scalar_t* __restrict h1, scalar_t* __restrict h2,
              scalar_t* __restrict spikes, scalar_t* __restrict membrane, int64_t length, int64_t n,
              scalar_t d, scalar_t kappa, scalar_t theta) {
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
    }
  }
}

}  // namespace

namespace sb3_spikeplastic_fast {

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> srm_loop_cpu(const at::Tensor& synaptic,
                                                                      const at::Tensor& h1, const at::Tensor& h2,
                                                                      double d, double kappa, double theta) {
  check_srm_operands(synaptic, h1, h2);
  const int64_t batch = synaptic.size(0), length = synaptic.size(1), n = synaptic.size(2);
  TORCH_CHECK(synaptic.device().is_cpu() && h1.device().is_cpu() && h2.device().is_cpu(),
              "srm_loop: CPU tensors only");

  const at::Tensor syn = synaptic.contiguous();
  at::Tensor spikes = at::empty_like(syn, at::MemoryFormat::Contiguous);
  at::Tensor membrane = at::empty_like(syn, at::MemoryFormat::Contiguous);
  at::Tensor new_h1 = h1.clone(at::MemoryFormat::Contiguous);
  at::Tensor new_h2 = h2.clone(at::MemoryFormat::Contiguous);

  const int64_t row = length * n;
  // about 32k element-steps per task, the ATen default grain
  const int64_t grain = row > 0 ? std::max<int64_t>(1, 32768 / row) : batch;

  AT_DISPATCH_FLOATING_TYPES(syn.scalar_type(), "srm_loop_cpu", [&] {
    const scalar_t d_s = static_cast<scalar_t>(d);
    const scalar_t kappa_s = static_cast<scalar_t>(kappa);
    const scalar_t theta_s = static_cast<scalar_t>(theta);
    const scalar_t* syn_p = syn.data_ptr<scalar_t>();
    scalar_t* h1_p = new_h1.data_ptr<scalar_t>();
    scalar_t* h2_p = new_h2.data_ptr<scalar_t>();
    scalar_t* s_p = spikes.data_ptr<scalar_t>();
    scalar_t* u_p = membrane.data_ptr<scalar_t>();
    const CallerDenormalMode mode;
    at::parallel_for(0, batch, grain, [&](int64_t begin, int64_t end) {
      const DenormalModeScope denormals(mode);
      for (int64_t b = begin; b < end; ++b) {
        srm_rows<scalar_t>(syn_p + b * row, h1_p + b * n, h2_p + b * n, s_p + b * row, u_p + b * row, length, n,
                           d_s, kappa_s, theta_s);
      }
    });
  });
  return std::make_tuple(spikes, membrane, new_h1, new_h2);
}

}  // namespace sb3_spikeplastic_fast

TORCH_LIBRARY(sb3_spikeplastic_fast, m) {
  m.def(
      "srm_loop(Tensor synaptic, Tensor h1, Tensor h2, float d, float kappa, float theta) "
      "-> (Tensor, Tensor, Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(sb3_spikeplastic_fast, CPU, m) {
  m.impl("srm_loop", &sb3_spikeplastic_fast::srm_loop_cpu);
}
