// One interval of a plastic SRM layer, forward and backward, each as one op (the CPU fast path of
// sb3_spikeplastic.layers.PlasticSRMLayer on the training path). The forward pass runs the same ATen ops and
// kernels as the eager layer, in the same order, so its spikes, membrane and states are bit-identical:
//
//     R = [S; h1; h2]                                   (B, L + 2, n_in): the spikes and the carried PSP state
//     filter first (n_in <= n_out):  F = K R,  syn = P(F[:L]),  (h1', h2') = F[L:]
//     otherwise:                     syn = Kpsp P(R),   (h1', h2') = Kend R
//     (s, u, refractory') = srm_loop(syn),  rho = SLAYER surrogate(u),  r_pre = mean_t S,  r_post = mean_t s
//
// with P the product X (W + alpha * E_b)^T (plastic_linear.cpp) or X W^T (a static layer) and K = [Kpsp; Kend]
// the interval's alpha-filter operator. The backward pass (the refractory path is not differentiated, as in
// SLAYER) with gs = dL/ds + dL/dr_post / L and G = gs * rho:
//
//     filter first:  dF[:L] = dP(G),  dF[L:] = [dh1'; dh2'],  dR = K^T dF
//     otherwise:     dR = dP(Kpsp^T G) + Kend^T [dh1'; dh2']
//     dS = dR[:L] + dL/dr_pre / L,  dh1 = dR[L],  dh2 = dR[L + 1]
//
// plus dW, dalpha, dE from the product's backward. One op each way replaces ~12 autograd nodes and ~25 Python
// calls per layer and interval, which dominate the small CPU networks' training step.

#include <ATen/ATen.h>
#include <torch/library.h>

#include "kernels.h"

#include <optional>
#include <vector>

namespace {

at::Tensor product(const at::Tensor& x, const at::Tensor& W, const std::optional<at::Tensor>& alpha,
                   const std::optional<at::Tensor>& E) {
  if (!alpha.has_value()) return at::matmul(x, W.t());
  return sb3_spikeplastic_fast::plastic_linear_forward(x, W, *alpha, *E);
}

// (dX or undefined, dW, dalpha or undefined, dE or undefined)
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> product_backward(
    const at::Tensor& grad, const at::Tensor& x, const at::Tensor& W, const std::optional<at::Tensor>& alpha,
    const std::optional<at::Tensor>& E, bool need_x) {
  if (!alpha.has_value()) {
    const at::Tensor dW = at::mm(grad.reshape({-1, grad.size(-1)}).t(), x.reshape({-1, x.size(-1)}));
    return std::make_tuple(need_x ? at::matmul(grad, W) : at::Tensor(), dW, at::Tensor(), at::Tensor());
  }
  return sb3_spikeplastic_fast::plastic_linear_backward(grad, x, W, *alpha, *E, need_x);
}

// -> spikes, membrane, psp h1', psp h2', refractory h1', refractory h2', r_pre, r_post, product input, surrogate
std::vector<at::Tensor> srm_interval_forward(const at::Tensor& x, const at::Tensor& h1, const at::Tensor& h2,
                                             const at::Tensor& ref_h1, const at::Tensor& ref_h2, const at::Tensor& W,
                                             const std::optional<at::Tensor>& alpha,
                                             const std::optional<at::Tensor>& E, const at::Tensor& op,
                                             const at::Tensor& psp_rows, const at::Tensor& end_rows,
                                             bool filter_first, double d, double kappa, double theta, double width,
                                             double scale) {
  TORCH_CHECK(x.dim() == 3 && op.dim() == 2 && op.size(0) == x.size(1) + 2,
              "srm_interval: spikes (B, L, n_in) and a (L + 2, L + 2) filter operator");
  TORCH_CHECK(alpha.has_value() == E.has_value(), "srm_interval: alpha and E come together");
  const at::NoGradGuard no_grad;
  const int64_t L = x.size(1);
  const at::Tensor rows = at::cat({x, h1.unsqueeze(1), h2.unsqueeze(1)}, 1);
  at::Tensor product_in, synaptic, end;
  if (filter_first) {
    const at::Tensor filtered = at::matmul(op, rows);
    product_in = filtered.narrow(1, 0, L);
    end = filtered.narrow(1, L, 2);
    synaptic = product(product_in, W, alpha, E);
  } else {
    product_in = rows;
    synaptic = at::matmul(psp_rows, product(rows, W, alpha, E));
    end = at::matmul(end_rows, rows);
  }
  auto [spikes, membrane, rh1, rh2] = sb3_spikeplastic_fast::srm_loop_cpu(synaptic, ref_h1, ref_h2, d, kappa, theta);
  // neurons.slayer_surrogate, op for op
  at::Tensor surrogate = at::sub(membrane, theta).abs_().div_(-width).exp_().mul_(scale / width);
  return {spikes, membrane, end.select(1, 0), end.select(1, 1), rh1, rh2, x.mean(1), spikes.mean(1), product_in,
          surrogate};
}

// -> dS, dh1, dh2 (empty unless need_rows), dW, dalpha, dE (empty for a static layer)
std::vector<at::Tensor> srm_interval_backward(const at::Tensor& d_spikes, const at::Tensor& d_h1,
                                              const at::Tensor& d_h2, const at::Tensor& d_r_pre,
                                              const at::Tensor& d_r_post, const at::Tensor& product_in,
                                              const at::Tensor& W, const std::optional<at::Tensor>& alpha,
                                              const std::optional<at::Tensor>& E, const at::Tensor& surrogate,
                                              const at::Tensor& op, const at::Tensor& psp_rows,
                                              const at::Tensor& end_rows, bool filter_first, bool need_rows) {
  const at::NoGradGuard no_grad;
  const int64_t L = surrogate.size(1);
  const at::Tensor d_synaptic = (d_spikes + (d_r_post / L).unsqueeze(1)) * surrogate;
  at::Tensor d_rows;
  at::Tensor d_in, dW, d_alpha, dE;
  if (filter_first) {
    std::tie(d_in, dW, d_alpha, dE) = product_backward(d_synaptic, product_in, W, alpha, E, need_rows);
    if (need_rows) d_rows = at::matmul(op.t(), at::cat({d_in, d_h1.unsqueeze(1), d_h2.unsqueeze(1)}, 1));
  } else {
    std::tie(d_in, dW, d_alpha, dE) =
        product_backward(at::matmul(psp_rows.t(), d_synaptic), product_in, W, alpha, E, need_rows);
    if (need_rows) d_rows = d_in + at::matmul(end_rows.t(), at::stack({d_h1, d_h2}, 1));
  }
  const at::Tensor none = at::empty({0}, W.options());
  at::Tensor d_x = none, d_rh1 = none, d_rh2 = none;
  if (need_rows) {
    d_x = d_rows.narrow(1, 0, L) + (d_r_pre / L).unsqueeze(1);
    d_rh1 = d_rows.select(1, L);
    d_rh2 = d_rows.select(1, L + 1);
  }
  return {d_x, d_rh1, d_rh2, dW, d_alpha.defined() ? d_alpha : none, dE.defined() ? dE : none};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(sb3_spikeplastic_fast, m) {
  m.def(
      "srm_interval_forward(Tensor x, Tensor h1, Tensor h2, Tensor ref_h1, Tensor ref_h2, Tensor W, Tensor? alpha, "
      "Tensor? E, Tensor op, Tensor psp_rows, Tensor end_rows, bool filter_first, float d, float kappa, "
      "float theta, float width, float scale) -> Tensor[]");
  m.def(
      "srm_interval_backward(Tensor d_spikes, Tensor d_h1, Tensor d_h2, Tensor d_r_pre, Tensor d_r_post, "
      "Tensor product_in, Tensor W, Tensor? alpha, Tensor? E, Tensor surrogate, Tensor op, Tensor psp_rows, "
      "Tensor end_rows, bool filter_first, bool need_rows) -> Tensor[]");
}

TORCH_LIBRARY_IMPL(sb3_spikeplastic_fast, CPU, m) {
  m.impl("srm_interval_forward", &srm_interval_forward);
  m.impl("srm_interval_backward", &srm_interval_backward);
}
