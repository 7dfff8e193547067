// The compiled CPU kernels that other kernels of this extension call directly (without the dispatcher).
#pragma once

#include <ATen/core/Tensor.h>

#include <functional>
#include <tuple>
#include <vector>

namespace sb3_spikeplastic_fast {

// srm_loop.cpp: the threshold/refractory recursion over an interval -> (spikes, membrane, h1, h2).
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> srm_loop_cpu(const at::Tensor& synaptic,
                                                                      const at::Tensor& h1, const at::Tensor& h2,
                                                                      double d, double kappa, double theta);
// The same loop as the fused interval needs it -> (spikes, membrane, h1, h2, surrogate, rate): also SLAYER's
// surrogate gradient of the membrane (neurons.slayer_surrogate) when need_surrogate (an empty tensor otherwise),
// and the spike rates over the interval, spikes.mean(1), bit-identical.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> srm_loop_interval_cpu(
    const at::Tensor& synaptic, const at::Tensor& h1, const at::Tensor& h2, double d, double kappa, double theta,
    double width, double scale, bool need_surrogate);

// plastic_linear.cpp: Y[b] = X[b] (W + alpha * E[b])^T and, for carried rows C (B, 2, n_in) when given, Yc[b] =
// C[b] (W + alpha * E[b])^T -> (Y, Yc); its gradients, dE starting from dE_init when it is given (a gradient of E
// from elsewhere, added in the same pass).
struct ProductGradients {
  at::Tensor dX, dW, dalpha, dE, dC;  // dX and dC undefined or empty unless asked for (dC also without C)
};
std::tuple<at::Tensor, at::Tensor> plastic_linear_forward(const at::Tensor& X, const at::Tensor& W,
                                                          const at::Tensor& alpha, const at::Tensor& E,
                                                          const at::Tensor& C = at::Tensor());
ProductGradients plastic_linear_backward(const at::Tensor& grad, const at::Tensor& grad_c, const at::Tensor& X,
                                         const at::Tensor& W, const at::Tensor& alpha, const at::Tensor& E,
                                         const at::Tensor& C, bool need_x_grad,
                                         const at::Tensor& dE_init = at::Tensor());

// The same product with the previous intervals' trace updates deferred into its pass over the trace: E_t = E with
// clamp((1 - eta) E + (eta p0) (x) q0) applied, then likewise (p1, q1) (each pair when given), written out when write,
// and the Oja term's row sums r = E_t q; its backward pass, whose fill_grad (if given) writes the rows of grad of
// environments [b0, b0 + n) just before they are multiplied. Each tensor is empty where it is not computed.
struct DeferredProduct {
  at::Tensor Y, Yc, E_t, r;
};
struct DeferredProductGradients {
  at::Tensor dX, dW, dalpha, dE, dq;
  at::Tensor dp0, dq0, dp1, dq1;  // of the pending updates
  at::Tensor deta;                // dL/deta of the pending updates
  at::Tensor dC;
};
DeferredProduct plastic_linear_deferred_forward(const at::Tensor& X, const at::Tensor& W, const at::Tensor& alpha,
                                                const at::Tensor& E, const at::Tensor& C, const at::Tensor& p0,
                                                const at::Tensor& q0, const at::Tensor& p1, const at::Tensor& q1,
                                                const at::Tensor& q, double eta, double e_max, bool write);
DeferredProductGradients plastic_linear_deferred_backward(
    const at::Tensor& grad, const at::Tensor& grad_c, const at::Tensor& X, const at::Tensor& W,
    const at::Tensor& alpha, const at::Tensor& E, const at::Tensor& C, const at::Tensor& p0, const at::Tensor& q0,
    const at::Tensor& p1, const at::Tensor& q1, const at::Tensor& q, const at::Tensor& dE_t, const at::Tensor& dr,
    bool need_x_grad, double eta, double e_max, bool write,
    const std::function<void(int64_t, int64_t)>& fill_grad = {});

// alpha_filter.cpp: the alpha filter of rows z (B, L, n) from the state (a, b) (each (B, n), undefined = zero) by its
// recurrence -> (psp (B, L, n), end state (B, 2, n)), as neurons.alpha_filter_operator's product with [z; a; b];
// and the adjoint, the operator's transpose: (dpsp, d_end_a, d_end_b) -> (dz (B, L, n), [da; db] (B, 2, n)).
std::tuple<at::Tensor, at::Tensor> alpha_filter_rows(const at::Tensor& z, const at::Tensor& a, const at::Tensor& b,
                                                     double d, double g);
std::tuple<at::Tensor, at::Tensor> alpha_filter_rows_adjoint(const at::Tensor& dpsp, const at::Tensor& da,
                                                             const at::Tensor& db, double d, double g);
// The same filter's end state alone and the rows' mean over the interval, in one pass over z -> (end state (B, 2, n),
// mean (B, n)).
std::tuple<at::Tensor, at::Tensor> alpha_filter_end_and_mean(const at::Tensor& z, const at::Tensor& a,
                                                             const at::Tensor& b, double d);

// trace_step.cpp: E' = clamp((1 - eta) E + (eta p) (x) pre), p = post - [E pre] -> (E', p), and its gradients
// (dE, dpost, dpre, deta).
std::tuple<at::Tensor, at::Tensor> trace_step_forward(const at::Tensor& E, const at::Tensor& post,
                                                     const at::Tensor& pre, double eta, double e_max, bool oja);
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> trace_step_backward(
    const at::Tensor& grad, const at::Tensor& E, const at::Tensor& p, const at::Tensor& pre, double eta,
    double e_max, bool oja);

}  // namespace sb3_spikeplastic_fast
