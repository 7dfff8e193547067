// CUDA SRM threshold/refractory recursion (the GPU fast path of sb3_spikeplastic.neurons.srm_spike_loop).
//
// The same recursion as srm_loop.cpp, per neuron and step t, in the tensor's dtype and in exactly this order:
//
//     h2 = (h2 + h1) * d
//     u  = syn[t] - (h2 * kappa)
//     s  = (u >= theta) ? 1 : 0
//     h1 = (h1 * d) + s
//
// Eager PyTorch runs each step as ~7 kernel launches, so an interval of T = 50 steps costs ~350 launches per
// layer and a GPU forward is bound by launch latency, not arithmetic. Here one thread owns one (row, neuron) and
// walks the T steps itself: one launch per layer and interval. Threads of a warp hold neighbouring neurons, so
// every load and store of a step is coalesced.
//
// Built with -fmad=false: no multiply-add is contracted, each operation is rounded on its own as in the
// separate eager kernels, and the results are bit-identical to the eager loop on the same GPU.

#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty_like.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include "srm_loop_checks.h"

#include <cstdint>
#include <tuple>

namespace {

template <typename scalar_t>
__global__ void srm_loop_kernel(const scalar_t* __restrict__ syn, const scalar_t* __restrict__ h1_in,
                                const scalar_t* __restrict__ h2_in, scalar_t* __restrict__ spikes,
                                scalar_t* __restrict__ membrane, scalar_t* __restrict__ h1_out,
                                scalar_t* __restrict__ h2_out, int64_t batch, int64_t length, int64_t n,
                                scalar_t d, scalar_t kappa, scalar_t theta) {
  const int64_t index = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (index >= batch * n) return;
  const int64_t row = index / n;
  const int64_t offset = row * length * n + (index - row * n);  // element (row, 0, neuron)
  scalar_t h1 = h1_in[index];
  scalar_t h2 = h2_in[index];
  for (int64_t t = 0; t < length; ++t) {
    const int64_t at = offset + t * n;
    h2 = (h2 + h1) * d;
    const scalar_t u = syn[at] - h2 * kappa;
    const scalar_t s = (u >= theta) ? scalar_t(1) : scalar_t(0);
    h1 = h1 * d + s;
    membrane[at] = u;
    spikes[at] = s;
  }
  h1_out[index] = h1;
  h2_out[index] = h2;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> srm_loop_cuda(const at::Tensor& synaptic,
                                                                       const at::Tensor& h1, const at::Tensor& h2,
                                                                       double d, double kappa, double theta) {
  check_srm_operands(synaptic, h1, h2);
  const int64_t batch = synaptic.size(0), length = synaptic.size(1), n = synaptic.size(2);
  TORCH_CHECK(synaptic.is_cuda() && h1.device() == synaptic.device() && h2.device() == synaptic.device(),
              "srm_loop: CUDA tensors on one device only");

  const c10::cuda::CUDAGuard guard(synaptic.device());
  const at::Tensor syn = synaptic.contiguous();
  const at::Tensor h1_c = h1.contiguous();
  const at::Tensor h2_c = h2.contiguous();
  at::Tensor spikes = at::empty_like(syn, at::MemoryFormat::Contiguous);
  at::Tensor membrane = at::empty_like(syn, at::MemoryFormat::Contiguous);
  at::Tensor new_h1 = at::empty_like(h1_c, at::MemoryFormat::Contiguous);
  at::Tensor new_h2 = at::empty_like(h2_c, at::MemoryFormat::Contiguous);
  const int64_t threads_total = batch * n;
  if (threads_total == 0) return std::make_tuple(spikes, membrane, h1_c.clone(), h2_c.clone());

  constexpr int threads = 128;
  const int64_t blocks = (threads_total + threads - 1) / threads;
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(syn.scalar_type(), "srm_loop_cuda", [&] {
    srm_loop_kernel<scalar_t><<<static_cast<unsigned int>(blocks), threads, 0, stream>>>(
        syn.data_ptr<scalar_t>(), h1_c.data_ptr<scalar_t>(), h2_c.data_ptr<scalar_t>(), spikes.data_ptr<scalar_t>(),
        membrane.data_ptr<scalar_t>(), new_h1.data_ptr<scalar_t>(), new_h2.data_ptr<scalar_t>(), batch, length, n,
        static_cast<scalar_t>(d), static_cast<scalar_t>(kappa), static_cast<scalar_t>(theta));
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return std::make_tuple(spikes, membrane, new_h1, new_h2);
}

}  // namespace

TORCH_LIBRARY(sb3_spikeplastic_cuda, m) {
  m.def(
      "srm_loop(Tensor synaptic, Tensor h1, Tensor h2, float d, float kappa, float theta) "
      "-> (Tensor spikes, Tensor membrane, Tensor h1, Tensor h2)");
}

TORCH_LIBRARY_IMPL(sb3_spikeplastic_cuda, CUDA, m) {
  m.impl("srm_loop", &srm_loop_cuda);
}
