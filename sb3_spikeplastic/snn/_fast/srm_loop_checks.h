// Operand checks shared by the CPU (srm_loop.cpp) and CUDA (srm_loop_cuda.cu) spike loops.
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

// synaptic (batch, length, n) and the refractory state h1, h2 (batch, n), float32 or float64 of one dtype.
inline void check_srm_operands(const at::Tensor& synaptic, const at::Tensor& h1, const at::Tensor& h2) {
  TORCH_CHECK(synaptic.dim() == 3, "srm_loop: synaptic must be (batch, length, n)");
  TORCH_CHECK(synaptic.scalar_type() == at::kFloat || synaptic.scalar_type() == at::kDouble,
              "srm_loop: float32 or float64 only");
  TORCH_CHECK(h1.scalar_type() == synaptic.scalar_type() && h2.scalar_type() == synaptic.scalar_type(),
              "srm_loop: state dtype must match synaptic dtype");
  TORCH_CHECK(h1.dim() == 2 && h1.size(0) == synaptic.size(0) && h1.size(1) == synaptic.size(2) &&
                  h2.sizes() == h1.sizes(),
              "srm_loop: state must be (batch, n)");
}
