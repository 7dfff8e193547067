// The compiled CPU kernels that other kernels of this extension call directly (without the dispatcher).
#pragma once

#include <ATen/core/Tensor.h>

#include <tuple>

namespace sb3_spikeplastic_fast {

// srm_loop.cpp: the threshold/refractory recursion over an interval -> (spikes, membrane, h1, h2).
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> srm_loop_cpu(const at::Tensor& synaptic,
                                                                      const at::Tensor& h1, const at::Tensor& h2,
                                                                      double d, double kappa, double theta);

// plastic_linear.cpp: Y[b] = X[b] (W + alpha * E[b])^T and its gradients (dX, dW, dalpha, dE).
at::Tensor plastic_linear_forward(const at::Tensor& X, const at::Tensor& W, const at::Tensor& alpha,
                                  const at::Tensor& E);
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> plastic_linear_backward(
    const at::Tensor& grad, const at::Tensor& X, const at::Tensor& W, const at::Tensor& alpha, const at::Tensor& E,
    bool need_x_grad);

}  // namespace sb3_spikeplastic_fast
