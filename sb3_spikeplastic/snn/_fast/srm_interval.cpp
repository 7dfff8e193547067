// One interval of a plastic SRM layer, forward and backward, each as one op (the CPU fast path of
// sb3_spikeplastic.layers.PlasticSRMLayer). The forward pass runs the same ATen ops and
// kernels as the eager layer, in the same order but for the filter (below):
//
//     R = [S; H],  H = [h1; h2]                          (B, L + 2, n_in): the spikes and the carried PSP state
//     filter first (n_in <= n_out):  F = K R,  syn = P(F[:L]),  (h1', h2') = F[L:]
//     otherwise:                     syn = Kpsp P(R),   (h1', h2') = Kend[:, :L] S + Kend[:, L:] H
//
// (a plastic layer that does not filter first multiplies H in the pass that builds its efficacy, beside S, instead
// of copying S and H into R; its end state (h1', h2') and r_pre come from one pass of the filter's recurrence over S)
//     (s, u, refractory', rho, r_post) = srm_loop(syn)  (in the same loop: rho, the SLAYER surrogate of u,
//     and r_post = mean_t s),  r_pre = mean_t S
//
// with P the product X (W + alpha * E_b)^T (plastic_linear.cpp) or X W^T (a static layer) and K = [Kpsp; Kend]
// the interval's alpha-filter operator, whose products with K and Kpsp (and their transposes) run as the filter's
// recurrence (alpha_filter.cpp: equal to float rounding, and faster than the (L + 2)-term products). The backward
// pass (the refractory path is not differentiated, as in SLAYER) with gs = dL/ds + dL/dr_post / L and G = gs * rho:
//
//     filter first:  dF[:L] = dP(G),  dF[L:] = [dh1'; dh2'],  dR = K^T dF
//     otherwise:     dR = dP(Kpsp^T G) + Kend^T [dh1'; dh2']
//     dS = dR[:L] + dL/dr_pre / L,  dh1 = dR[L],  dh2 = dR[L + 1]
//
// plus dW, dalpha, dE from the product's backward. One op each way replaces ~12 autograd nodes and ~25 Python
// calls per layer and interval, which dominate the small CPU networks' training step.
//
// With eta given (a layer with a built-in rule), the same op adds the rule's trace update (sb3_spikeplastic.plasticity,
// paper eqs. 6-16): post = r_post or M * r_post with M = W_m r_post (or tanh of it), pre = r_pre or the BCM term
// r_pre * (r_pre - (phi + psi)) with phi' = (1 - eta_phi) phi + eta_phi r_pre, then E' = trace_step(E, post, pre)
// (trace_step.cpp), op for op as the eager rule. Backward, the trace step's dE is added to the product's in the
// same pass over the trace, and the terms' gradients are chained by hand:
//
//     modulated:  dM = dpost * r_post (* (1 - M^2) for tanh),  dW_m = dM^T r_post,  dr_post += dpost * M + dM W_m
//     BCM:        dr_pre += dpre * (2 r_pre - (phi + psi)) + dphi' eta_phi,  dphi = -dpre r_pre + dphi' (1 - eta_phi),
//                 dpsi = sum_b -dpre r_pre,  deta_phi = sum dphi' (r_pre - phi)
//
// srm_interval_deferred_forward/backward (below) are the same interval with the trace update deferred to the next
// interval's pass over E, as the training sequences run it.

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "denormal_mode.h"
#include "kernels.h"

#include <functional>
#include <optional>
#include <vector>

namespace {

// The product of rows x and, when given, of the rows carried beside them: (x W_eff^T, carried W_eff^T or undefined).
std::pair<at::Tensor, at::Tensor> product(const at::Tensor& x, const at::Tensor& carried, const at::Tensor& W,
                                          const std::optional<at::Tensor>& alpha,
                                          const std::optional<at::Tensor>& E) {
  // a static layer's rows come whole (interval_forward)
  if (!alpha.has_value()) return {at::matmul(x, W.t()), at::Tensor()};
  auto [y, yc] = sb3_spikeplastic_fast::plastic_linear_forward(x, W, *alpha, *E, carried);
  return {y, carried.defined() ? yc : at::Tensor()};
}

// (dX or undefined, dW, dalpha or undefined, dE or undefined, dC or undefined)
using ProductGradients = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>;

// Fills the rows of environments [b0, b0 + n) of a gradient before a product reads them (plastic_linear's
// fill_grad); a product that cannot take it per environment fills them all first.
using RowFill = std::function<void(int64_t, int64_t)>;

void fill_rows_in_parallel(const RowFill& fill, int64_t B) {
  const CallerDenormalMode mode;
  at::parallel_for(0, B, 1, [&](int64_t begin, int64_t end) {
    const DenormalModeScope denormals(mode);
    fill(begin, end - begin);
  });
}

ProductGradients product_backward(const at::Tensor& grad, const at::Tensor& grad_c, const at::Tensor& x,
                                  const at::Tensor& carried, const at::Tensor& W,
                                  const std::optional<at::Tensor>& alpha, const std::optional<at::Tensor>& E,
                                  bool need_x, const at::Tensor& dE_init, const RowFill& fill) {
  if (fill) fill_rows_in_parallel(fill, grad.size(0));
  if (!alpha.has_value()) {
    const at::Tensor dW = at::mm(grad.reshape({-1, grad.size(-1)}).t(), x.reshape({-1, x.size(-1)}));
    return {need_x ? at::matmul(grad, W) : at::Tensor(), dW, at::Tensor(), at::Tensor(), at::Tensor()};
  }
  const std::vector<at::Tensor> g =
      sb3_spikeplastic_fast::plastic_linear_backward(grad, grad_c, x, W, *alpha, *E, carried, need_x, dE_init);
  return {g[0], g[1], g[2], g[3], g[4]};
}

// Autograd passes no gradient for an output that the loss does not reach (the output layer's spikes, a hidden
// layer's rates, a chunk's final state), where it would otherwise fill a zero tensor of the output's size. The
// backward pass takes such a gradient as an undefined tensor and reads it as zero:
at::Tensor given(const std::optional<at::Tensor>& t) { return t.has_value() ? *t : at::Tensor(); }

// a + b, with a missing a read as zero
at::Tensor plus(const at::Tensor& a, const at::Tensor& b) { return a.defined() ? a + b : b; }

at::Tensor or_zeros(const at::Tensor& t, const at::Tensor& like) { return t.defined() ? t : at::zeros_like(like); }

// dL/dsyn = (dL/ds + dL/dr_post / L) * rho in one pass over the interval, where the ATen expression
// (d_spikes + (d_r_post / L).unsqueeze(1)) * surrogate makes two and a broadcast: the same operations in the
// same order, so the same values. An undefined d_spikes or d_r_post is zero; d_spikes may be a view with gaps
// between its rows (the next layer's input gradient, a slice of its filter rows). The output is allocated first and
// its rows filled per environment (fill), so that a plastic product can fill each environment's rows just before it
// multiplies them, while they are in cache (RowFill).
class SynapticGradient {
 public:
  SynapticGradient(const at::Tensor& d_spikes, const at::Tensor& d_r_post, const at::Tensor& surrogate)
      : rho_(surrogate.contiguous()),
        ds_(!d_spikes.defined() || d_spikes.stride(2) == 1 ? d_spikes : d_spikes.contiguous()),
        dr_(d_r_post.defined() ? (d_r_post / surrogate.size(1)).contiguous() : at::Tensor()),
        out_(ds_.defined() || dr_.defined() ? at::empty_like(rho_, at::MemoryFormat::Contiguous)
                                            : at::zeros_like(rho_, at::MemoryFormat::Contiguous)) {}

  const at::Tensor& output() const { return out_; }

  // The rows of environments [b0, b0 + n).
  void fill(int64_t b0, int64_t n) const {
    if (!ds_.defined() && !dr_.defined()) return;  // zeros
    const int64_t L = rho_.size(1), width = rho_.size(2);
    AT_DISPATCH_FLOATING_TYPES(rho_.scalar_type(), "synaptic_gradient", [&] {
      const scalar_t* rho_p = rho_.const_data_ptr<scalar_t>();
      const scalar_t* ds_p = ds_.defined() ? ds_.const_data_ptr<scalar_t>() : nullptr;
      const scalar_t* dr_p = dr_.defined() ? dr_.const_data_ptr<scalar_t>() : nullptr;
      const int64_t ds_b = ds_.defined() ? ds_.stride(0) : 0, ds_t = ds_.defined() ? ds_.stride(1) : 0;
      scalar_t* out_p = out_.data_ptr<scalar_t>();
      for (int64_t b = b0; b < b0 + n; ++b) {
        for (int64_t t = 0; t < L; ++t) {
          const scalar_t* __restrict r = rho_p + (b * L + t) * width;
          scalar_t* __restrict o = out_p + (b * L + t) * width;
          const scalar_t* __restrict s = ds_p != nullptr ? ds_p + b * ds_b + t * ds_t : nullptr;
          const scalar_t* __restrict q = dr_p != nullptr ? dr_p + b * width : nullptr;
          if (s != nullptr && q != nullptr) {
            for (int64_t j = 0; j < width; ++j) o[j] = (s[j] + q[j]) * r[j];
          } else if (s != nullptr) {
            for (int64_t j = 0; j < width; ++j) o[j] = s[j] * r[j];
          } else {
            for (int64_t j = 0; j < width; ++j) o[j] = q[j] * r[j];
          }
        }
      }
    });
  }

  // Every row, split between threads.
  const at::Tensor& fill_all() const {
    fill_rows_in_parallel([this](int64_t b0, int64_t n) { fill(b0, n); }, out_.size(0));
    return out_;
  }

 private:
  at::Tensor rho_, ds_, dr_, out_;
};

// -> spikes, membrane, psp h1', psp h2', refractory h1', refractory h2', r_pre, r_post, product input, surrogate,
// carried rows (below; empty when there are none)
//
// The product P of the interval's rows: (rows, carried rows or undefined) -> (P of rows, P of the carried rows or
// undefined). With carries (a plastic layer whose product takes its spikes, with many spike rows:
// layers.PlasticSRMLayer.carries_state), the carried PSP state [h1; h2] is multiplied beside the spikes in the pass
// that builds the efficacy, so that the spikes are not copied into one block of L + 2 rows with it (and stay binary
// for the spike products); the backward pass then takes x as the product's input and the carried rows apart.
using Projection = std::function<std::pair<at::Tensor, at::Tensor>(const at::Tensor&, const at::Tensor&)>;

// The alpha filter's recurrence constants (d, g = c d) as its operator holds them (neurons.alpha_filter_matrices):
// d is v1[L - 2] (d^L itself for L = 1), g is g2[0].
std::pair<double, double> filter_constants(const at::Tensor& psp_rows, const at::Tensor& end_rows) {
  const int64_t L = psp_rows.size(0);
  const auto entry = [](const at::Tensor& m, int64_t i, int64_t j) {
    return AT_DISPATCH_FLOATING_TYPES(m.scalar_type(), "filter_constants", [&] {
      return static_cast<double>(m.const_data_ptr<scalar_t>()[i * m.stride(0) + j * m.stride(1)]);
    });
  };
  return {entry(end_rows, 0, L >= 2 ? L - 2 : L), entry(psp_rows, 0, L + 1)};
}

// The interval's input rates r_pre = mean_t x and, for a layer that multiplies its spikes before it filters, the
// PSP state at the interval's end (the filter's recurrence over x from (h1, h2)), both from one pass over x; end is
// undefined for a layer that filters first (its filter's pass gives it).
struct IntervalInputs {
  at::Tensor r_pre, end;
};

IntervalInputs interval_inputs(const at::Tensor& x, const at::Tensor& h1, const at::Tensor& h2,
                               const at::Tensor& psp_rows, const at::Tensor& end_rows, bool filter_first) {
  TORCH_CHECK(x.dim() == 3 && psp_rows.dim() == 2 && psp_rows.size(0) == x.size(1) &&
                  psp_rows.size(1) == x.size(1) + 2 && end_rows.dim() == 2 && end_rows.size(0) == 2 &&
                  end_rows.size(1) == x.size(1) + 2,
              "srm_interval: spikes (B, L, n_in) and the filter operator's (L, L + 2) and (2, L + 2) rows");
  const at::NoGradGuard no_grad;
  if (filter_first) return {x.mean(1), at::Tensor()};
  auto [end, r_pre] = sb3_spikeplastic_fast::alpha_filter_end_and_mean(
      x, h1, h2, filter_constants(psp_rows, end_rows).first);
  return {r_pre, end};
}

std::vector<at::Tensor> interval_forward(const at::Tensor& x, const at::Tensor& h1, const at::Tensor& h2,
                                         const at::Tensor& ref_h1, const at::Tensor& ref_h2, const Projection& project,
                                         bool carries, const at::Tensor& psp_rows,
                                         const at::Tensor& end_rows, bool filter_first, double d, double kappa,
                                         double theta, double width, double scale, bool need_surrogate,
                                         const IntervalInputs& inputs) {
  const at::NoGradGuard no_grad;
  const int64_t L = x.size(1);
  const auto [psp_d, psp_g] = filter_constants(psp_rows, end_rows);
  at::Tensor product_in, synaptic, end = inputs.end, carried = at::empty({0}, x.options());
  if (filter_first) {
    std::tie(product_in, end) = sb3_spikeplastic_fast::alpha_filter_rows(x, h1, h2, psp_d, psp_g);
    synaptic = project(product_in, at::Tensor()).first;
  } else if (carries) {
    carried = at::stack({h1, h2}, 1);
    product_in = x;
    const auto [y, yc] = project(x, carried);
    synaptic = std::get<0>(sb3_spikeplastic_fast::alpha_filter_rows(y, yc.select(1, 0), yc.select(1, 1), psp_d,
                                                                    psp_g));
  } else {
    product_in = at::cat({x, h1.unsqueeze(1), h2.unsqueeze(1)}, 1);
    const at::Tensor y = project(product_in, at::Tensor()).first;
    synaptic = std::get<0>(sb3_spikeplastic_fast::alpha_filter_rows(y.narrow(1, 0, L), y.select(1, L),
                                                                    y.select(1, L + 1), psp_d, psp_g));
  }
  // the surrogate (neurons.slayer_surrogate) only for training: in rollouts it would be the layer's largest cost
  auto [spikes, membrane, rh1, rh2, surrogate, r_post] = sb3_spikeplastic_fast::srm_loop_interval_cpu(
      synaptic, ref_h1, ref_h2, d, kappa, theta, width, scale, need_surrogate);
  return {spikes, membrane, end.select(1, 0), end.select(1, 1), rh1, rh2, inputs.r_pre, r_post,
          product_in, surrogate, carried};
}

// -> dS, dh1, dh2 (empty unless need_rows), dW, dalpha, dE (empty for a static layer); dE_init: a gradient of E
// from elsewhere, added to the product's. Undefined output gradients are zero.
// The product's backward pass: (dL/dP of the rows, of the carried rows (undefined without), need_rows) -> (dX or
// undefined, dW, dalpha or undefined, dE or undefined, dC or undefined)
using ProjectionBackward =
    std::function<ProductGradients(const at::Tensor&, const at::Tensor&, bool, const RowFill&)>;

std::vector<at::Tensor> interval_backward(const at::Tensor& d_spikes, const at::Tensor& d_h1, const at::Tensor& d_h2,
                                          const at::Tensor& d_r_pre, const at::Tensor& d_r_post,
                                          const at::Tensor& product_in, const at::Tensor& carried,
                                          const ProjectionBackward& project_backward, const at::Tensor& W,
                                          const at::Tensor& surrogate,
                                          const at::Tensor& psp_rows, const at::Tensor& end_rows, bool filter_first,
                                          bool need_rows) {
  const at::NoGradGuard no_grad;
  const int64_t L = surrogate.size(1);
  const SynapticGradient synaptic(d_spikes, d_r_post, surrogate);
  const auto [psp_d, psp_g] = filter_constants(psp_rows, end_rows);
  const at::Tensor like = product_in.select(1, 0);  // (B, n_in), the PSP state's shape
  at::Tensor d_x, d_state;                          // (B, L, n_in) and (B, 2, n_in) when need_rows
  at::Tensor d_in, dW, d_alpha, dE, d_c;
  if (filter_first) {
    // each environment's dL/dsyn written just before its product reads it
    std::tie(d_in, dW, d_alpha, dE, d_c) = project_backward(
        synaptic.output(), at::Tensor(), need_rows, [&](int64_t b0, int64_t n) { synaptic.fill(b0, n); });
    if (need_rows) {
      std::tie(d_x, d_state) = sb3_spikeplastic_fast::alpha_filter_rows_adjoint(d_in, d_h1, d_h2, psp_d, psp_g);
    }
  } else {
    // (B, L, n_out) and (B, 2, n_out)
    const auto [d_product, d_product_state] = sb3_spikeplastic_fast::alpha_filter_rows_adjoint(
        synaptic.fill_all(), at::Tensor(), at::Tensor(), psp_d, psp_g);
    const bool carries = carried.numel() > 0;
    if (carries) {
      std::tie(d_in, dW, d_alpha, dE, d_c) = project_backward(d_product, d_product_state, need_rows, {});
    } else {
      std::tie(d_in, dW, d_alpha, dE, d_c) =
          project_backward(at::cat({d_product, d_product_state}, 1), at::Tensor(), need_rows, {});
    }
    if (need_rows) {
      const at::Tensor d_end = at::stack({or_zeros(d_h1, like), or_zeros(d_h2, like)}, 1);
      d_x = d_in.narrow(1, 0, L) + at::matmul(end_rows.narrow(1, 0, L).t(), d_end);
      d_state = (carries ? d_c : d_in.narrow(1, L, 2)) + at::matmul(end_rows.narrow(1, L, 2).t(), d_end);
    }
  }
  const at::Tensor none = at::empty({0}, W.options());
  at::Tensor d_rh1 = none, d_rh2 = none;
  if (need_rows) {
    if (d_r_pre.defined()) d_x = d_x + (d_r_pre / L).unsqueeze(1);
    d_rh1 = d_state.select(1, 0);
    d_rh2 = d_state.select(1, 1);
  } else {
    d_x = none;
  }
  return {d_x, d_rh1, d_rh2, dW, d_alpha.defined() ? d_alpha : none, dE.defined() ? dE : none};
}

// Modulation forms of the rule terms (plasticity.MODULATION_FORMS, 0 for an unmodulated rule).
constexpr int64_t kUnmodulated = 0, kTanh = 2;

// The rule's presynaptic term (plasticity.bcm_presynaptic_term and bcm_threshold_update with phi, else r_pre) ->
// (pre, phi' or undefined).
std::pair<at::Tensor, at::Tensor> presynaptic_term(const at::Tensor& r_pre, const std::optional<at::Tensor>& phi,
                                                   const std::optional<at::Tensor>& eta_phi,
                                                   const std::optional<at::Tensor>& psi) {
  if (!phi.has_value()) return {r_pre, at::empty({0}, r_pre.options())};
  return {r_pre * (r_pre - (*phi + *psi)), at::rsub(*eta_phi, 1) * *phi + *eta_phi * r_pre};
}

// The rule's postsynaptic term (plasticity.modulatory_signal: M * r_post with M = W_m r_post or its tanh, else
// r_post) -> (post, M or an empty tensor).
std::pair<at::Tensor, at::Tensor> postsynaptic_term(const at::Tensor& r_post, const std::optional<at::Tensor>& w_m,
                                                    int64_t modulation) {
  if (modulation == kUnmodulated) return {r_post, at::empty({0}, r_post.options())};
  at::Tensor m = at::matmul(r_post, w_m->t());
  if (modulation == kTanh) m = at::tanh(m);
  return {m * r_post, m};
}

// The postsynaptic term's backward pass: adds to d_rpost, sets d_wm (unchanged without modulation).
void postsynaptic_backward(const at::Tensor& d_post, const at::Tensor& r_post, const std::optional<at::Tensor>& m,
                           const std::optional<at::Tensor>& w_m, int64_t modulation, at::Tensor& d_rpost,
                           at::Tensor& d_wm) {
  if (modulation == kUnmodulated) {
    d_rpost = plus(d_rpost, d_post);
    return;
  }
  at::Tensor d_m = d_post * r_post;
  d_rpost = plus(d_rpost, d_post * *m);
  if (modulation == kTanh) d_m = d_m * (1 - *m * *m);
  d_wm = at::mm(d_m.t(), r_post);
  d_rpost = d_rpost + at::mm(d_m, *w_m);
}

// The presynaptic term's backward pass: adds to d_rpre, sets d_phi, d_psi, d_eta_phi (unchanged without phi).
void presynaptic_backward(const at::Tensor& d_pre, const at::Tensor& r_pre, const std::optional<at::Tensor>& phi,
                          const std::optional<at::Tensor>& eta_phi, const std::optional<at::Tensor>& psi,
                          const at::Tensor& d_new_phi, at::Tensor& d_rpre, at::Tensor& d_phi, at::Tensor& d_psi,
                          at::Tensor& d_eta_phi) {
  if (!phi.has_value()) {
    d_rpre = plus(d_rpre, d_pre);
    return;
  }
  const at::Tensor d_new_phi_or_zero = or_zeros(d_new_phi, *phi);
  const at::Tensor d_threshold = -(d_pre * r_pre);  // of phi + psi
  d_rpre = plus(d_rpre, d_pre * (2 * r_pre - (*phi + *psi))) + d_new_phi_or_zero * *eta_phi;
  d_phi = d_threshold + d_new_phi_or_zero * at::rsub(*eta_phi, 1);
  d_psi = d_threshold.sum(0);
  d_eta_phi = (d_new_phi_or_zero * (r_pre - *phi)).sum();
}

// The interval, then (when eta is given: a built-in rule's layer) the trace update. -> spikes, membrane, psp h1',
// psp h2', refractory h1', refractory h2', r_pre, r_post, E', phi' (empty unless BCM), then for the backward pass
// the product's input, the surrogate (empty unless need_surrogate), p (the trace step's post - [E pre]), pre and M
// (empty unless modulated); E', p and pre are empty without a trace update.
std::vector<at::Tensor> srm_interval_forward(
    const at::Tensor& x, const at::Tensor& h1, const at::Tensor& h2, const at::Tensor& ref_h1, const at::Tensor& ref_h2,
    const at::Tensor& W, const std::optional<at::Tensor>& alpha, const std::optional<at::Tensor>& E,
    const std::optional<at::Tensor>& phi, const std::optional<at::Tensor>& eta,
    const std::optional<at::Tensor>& eta_phi, const std::optional<at::Tensor>& psi,
    const std::optional<at::Tensor>& w_m, const at::Tensor& psp_rows,
    const at::Tensor& end_rows, bool filter_first, double d, double kappa, double theta, double width, double scale,
    double e_max, bool oja, int64_t modulation, bool need_surrogate, bool carry_state) {
  TORCH_CHECK(!eta.has_value() || E.has_value(), "srm_interval: a trace update needs E");
  TORCH_CHECK(phi.has_value() == eta_phi.has_value() && phi.has_value() == psi.has_value(),
              "srm_interval: phi, eta_phi and psi come together (BCM rules)");
  TORCH_CHECK((modulation == kUnmodulated) != w_m.has_value() && modulation >= kUnmodulated && modulation <= kTanh,
              "srm_interval: W_m with a modulation form 1 (linear) or 2 (tanh), or neither");
  const at::NoGradGuard no_grad;
  TORCH_CHECK(alpha.has_value() == E.has_value(), "srm_interval: alpha and E come together");
  std::vector<at::Tensor> out = interval_forward(
      x, h1, h2, ref_h1, ref_h2,
      [&](const at::Tensor& rows, const at::Tensor& carried) { return product(rows, carried, W, alpha, E); },
      carry_state && alpha.has_value(), psp_rows, end_rows, filter_first, d, kappa, theta, width, scale,
      need_surrogate, interval_inputs(x, h1, h2, psp_rows, end_rows, filter_first));
  const at::Tensor carried = out.back();
  out.pop_back();
  const at::Tensor none = at::empty({0}, W.options());
  at::Tensor new_E = none, new_phi = none, p = none, pre = none, m = none;
  if (eta.has_value()) {
    at::Tensor post;
    std::tie(pre, new_phi) = presynaptic_term(out[6], phi, eta_phi, psi);
    std::tie(post, m) = postsynaptic_term(out[7], w_m, modulation);
    std::tie(new_E, p) = sb3_spikeplastic_fast::trace_step_forward(*E, post, pre, eta->item<double>(), e_max, oja);
  }
  out.insert(out.begin() + 8, {new_E, new_phi});
  out.insert(out.end(), {p, pre, m, carried});
  return out;
}

// -> dS, dh1, dh2 (empty unless need_rows), dW, dalpha, dE (empty for a static layer), dphi, deta_phi, dpsi (empty
// unless BCM), deta (empty without a trace update), dW_m (empty unless modulated)
std::vector<at::Tensor> srm_interval_backward(
    const std::optional<at::Tensor>& d_spikes, const std::optional<at::Tensor>& d_h1,
    const std::optional<at::Tensor>& d_h2, const std::optional<at::Tensor>& d_r_pre,
    const std::optional<at::Tensor>& d_r_post, const std::optional<at::Tensor>& d_new_E,
    const std::optional<at::Tensor>& d_new_phi, const at::Tensor& product_in, const at::Tensor& carried,
    const at::Tensor& W, const std::optional<at::Tensor>& alpha,
    const std::optional<at::Tensor>& E, const at::Tensor& surrogate, const at::Tensor& p, const at::Tensor& pre,
    const std::optional<at::Tensor>& m, const at::Tensor& r_pre, const at::Tensor& r_post,
    const std::optional<at::Tensor>& phi, const std::optional<at::Tensor>& eta,
    const std::optional<at::Tensor>& eta_phi, const std::optional<at::Tensor>& psi,
    const std::optional<at::Tensor>& w_m, const at::Tensor& psp_rows,
    const at::Tensor& end_rows, bool filter_first, bool need_rows, double e_max, bool oja, int64_t modulation) {
  const at::NoGradGuard no_grad;
  const at::Tensor none = at::empty({0}, W.options());
  at::Tensor d_rpost = given(d_r_post), d_rpre = given(d_r_pre), dE_trace, d_eta = none,
             d_wm = none, d_phi = none, d_eta_phi = none, d_psi = none;
  if (eta.has_value()) {
    at::Tensor d_post, d_pre;
    std::tie(dE_trace, d_post, d_pre, d_eta) =
        sb3_spikeplastic_fast::trace_step_backward(or_zeros(given(d_new_E), *E), *E, p, pre, eta->item<double>(),
                                                   e_max, oja);
    postsynaptic_backward(d_post, r_post, m, w_m, modulation, d_rpost, d_wm);
    presynaptic_backward(d_pre, r_pre, phi, eta_phi, psi, given(d_new_phi), d_rpre, d_phi, d_psi, d_eta_phi);
  }
  std::vector<at::Tensor> grads = interval_backward(
      given(d_spikes), given(d_h1), given(d_h2), d_rpre, d_rpost, product_in, carried,
      [&](const at::Tensor& grad, const at::Tensor& grad_c, bool need_x, const RowFill& fill) {
        return product_backward(grad, grad_c, product_in, carried.numel() > 0 ? carried : at::Tensor(), W, alpha, E,
                                need_x, dE_trace, fill);
      },
      W, surrogate, psp_rows, end_rows, filter_first, need_rows);
  grads.insert(grads.end(), {d_phi, d_eta_phi, d_psi, d_eta, d_wm});
  return grads;
}


// The deferred form (a built-in rule's layer inside a training sequence, layers.PlasticSRMLayer with
// defer_update): the previous intervals' trace updates, clamp((1 - eta) E + (eta p) (x) q) for each pending (p, q),
// oldest first, run in this interval's pass over E (plastic_linear_deferred_forward), and this interval's update is
// returned as (p, q = pre) for the next. Each interval then reads its trace once forward and once backward, where the
// update in its own pass reads it again. Without a pending update E is the trace itself. The trace the interval used
// is written out only when write_trace: a sequence keeps every other trace and recomputes the others from the one
// before and the two updates since. The values are those of srm_interval_forward bit for bit. -> as
// srm_interval_forward, with E_t (the trace this interval used; empty unless written) in the place of E', then p and
// q as outputs of their own (B, n_out), (B, n_in) at the end.
std::vector<at::Tensor> srm_interval_deferred_forward(
    const at::Tensor& x, const at::Tensor& h1, const at::Tensor& h2, const at::Tensor& ref_h1, const at::Tensor& ref_h2,
    const at::Tensor& W, const at::Tensor& alpha, const at::Tensor& E, const std::optional<at::Tensor>& p_first,
    const std::optional<at::Tensor>& q_first, const std::optional<at::Tensor>& p_second,
    const std::optional<at::Tensor>& q_second, const std::optional<at::Tensor>& phi, const at::Tensor& eta,
    const std::optional<at::Tensor>& eta_phi, const std::optional<at::Tensor>& psi,
    const std::optional<at::Tensor>& w_m, const at::Tensor& psp_rows,
    const at::Tensor& end_rows, bool filter_first, double d, double kappa, double theta, double width, double scale,
    double e_max, bool oja, int64_t modulation, bool need_surrogate, bool write_trace, bool carry_state) {
  TORCH_CHECK(phi.has_value() == eta_phi.has_value() && phi.has_value() == psi.has_value(),
              "srm_interval: phi, eta_phi and psi come together (BCM rules)");
  TORCH_CHECK((modulation == kUnmodulated) != w_m.has_value() && modulation >= kUnmodulated && modulation <= kTanh,
              "srm_interval: W_m with a modulation form 1 (linear) or 2 (tanh), or neither");
  const at::NoGradGuard no_grad;
  const double eta_value = eta.item<double>();
  const IntervalInputs inputs = interval_inputs(x, h1, h2, psp_rows, end_rows, filter_first);
  at::Tensor pre, new_phi, post, m;  // not structured bindings: the lambda below captures pre (C++17)
  std::tie(pre, new_phi) = presynaptic_term(inputs.r_pre, phi, eta_phi, psi);
  at::Tensor E_t, r;
  std::vector<at::Tensor> out = interval_forward(
      x, h1, h2, ref_h1, ref_h2,
      [&](const at::Tensor& rows, const at::Tensor& carried) {
        const std::vector<at::Tensor> y = sb3_spikeplastic_fast::plastic_linear_deferred_forward(
            rows, W, alpha, E, carried, given(p_first), given(q_first), given(p_second), given(q_second),
            oja ? pre : at::Tensor(), eta_value, e_max, write_trace);
        E_t = y[2];
        r = y[3];
        return std::make_pair(y[0], carried.defined() ? y[1] : at::Tensor());
      },
      carry_state, psp_rows, end_rows, filter_first, d, kappa, theta, width, scale, need_surrogate, inputs);
  const at::Tensor carried = out.back();
  out.pop_back();
  std::tie(post, m) = postsynaptic_term(out[7], w_m, modulation);
  const at::Tensor p = oja ? post - r : post;
  out.insert(out.begin() + 8, {E_t, new_phi});
  // p and q as outputs of their own: without Oja's term or BCM's they are r_post and r_pre themselves
  const at::Tensor p_next = p.is_same(out[7]) ? p.clone() : p, q_next = pre.is_same(out[6]) ? pre.clone() : pre;
  out.insert(out.end(), {p, pre, m, p_next, q_next, carried});
  return out;
}

// The backward pass of srm_interval_deferred_forward. d_E_t is the gradient of the trace the interval passed on (E_t
// when written, else E itself), d_p and d_q the gradients of the returned update (p, q). -> as srm_interval_backward
// (dE is dL/dE, the input trace), then dL/dp and dL/dq of each pending update (empty where none).
std::vector<at::Tensor> srm_interval_deferred_backward(
    const std::optional<at::Tensor>& d_spikes, const std::optional<at::Tensor>& d_h1,
    const std::optional<at::Tensor>& d_h2, const std::optional<at::Tensor>& d_r_pre,
    const std::optional<at::Tensor>& d_r_post, const std::optional<at::Tensor>& d_E_t,
    const std::optional<at::Tensor>& d_new_phi, const std::optional<at::Tensor>& d_p_next,
    const std::optional<at::Tensor>& d_q, const at::Tensor& product_in, const at::Tensor& carried,
    const at::Tensor& W, const at::Tensor& alpha, const at::Tensor& E, const std::optional<at::Tensor>& p_first,
    const std::optional<at::Tensor>& q_first,
    const std::optional<at::Tensor>& p_second, const std::optional<at::Tensor>& q_second,
    const at::Tensor& surrogate, const at::Tensor& p, const at::Tensor& pre, const std::optional<at::Tensor>& m,
    const at::Tensor& r_pre, const at::Tensor& r_post, const std::optional<at::Tensor>& phi, const at::Tensor& eta,
    const std::optional<at::Tensor>& eta_phi, const std::optional<at::Tensor>& psi,
    const std::optional<at::Tensor>& w_m, const at::Tensor& psp_rows,
    const at::Tensor& end_rows, bool filter_first, bool need_rows, double e_max, bool oja, int64_t modulation,
    bool write_trace) {
  const at::NoGradGuard no_grad;
  const at::Tensor none = at::empty({0}, W.options());
  const double eta_value = eta.item<double>();
  // p = post - r (Oja) or post
  const at::Tensor d_p = d_p_next.has_value() ? *d_p_next : at::zeros_like(p);
  at::Tensor d_eta = at::zeros({}, W.options());
  at::Tensor d_rpost = given(d_r_post), d_rpre = given(d_r_pre), d_wm = none, d_phi = none, d_eta_phi = none,
             d_psi = none;
  postsynaptic_backward(d_p, r_post, m, w_m, modulation, d_rpost, d_wm);
  std::vector<at::Tensor> product_grads;
  std::vector<at::Tensor> grads = interval_backward(
      given(d_spikes), given(d_h1), given(d_h2), at::Tensor(), d_rpost, product_in, carried,
      [&](const at::Tensor& grad, const at::Tensor& grad_c, bool need_x, const RowFill& fill) {
        product_grads = sb3_spikeplastic_fast::plastic_linear_deferred_backward(
            grad, grad_c, product_in, W, alpha, E, carried.numel() > 0 ? carried : at::Tensor(), given(p_first),
            given(q_first), given(p_second), given(q_second), oja ? pre : at::Tensor(), given(d_E_t),
            oja ? -d_p : at::Tensor(), need_x, eta_value, e_max, write_trace, fill);
        const std::vector<at::Tensor>& g = product_grads;
        return ProductGradients{g[0], g[1], g[2], g[3], g[10]};
      },
      W, surrogate, psp_rows, end_rows, filter_first, need_rows);
  // product_grads: dX, dW, dalpha, dE, dq (the Oja row sums'), dq0, dp0, dq1, dp1, deta of the pending updates, dC
  // dL/dpre: from the next interval's update and from the Oja term's row sums; then the rates (only now: the row
  // sums' gradient comes out of the product's pass)
  at::Tensor d_pre = given(d_q);
  if (oja) d_pre = plus(d_pre, product_grads[4]);
  if (!d_pre.defined()) d_pre = at::zeros_like(pre);
  presynaptic_backward(d_pre, r_pre, phi, eta_phi, psi, given(d_new_phi), d_rpre, d_phi, d_psi, d_eta_phi);
  if (need_rows && d_rpre.defined()) {
    const int64_t L = surrogate.size(1);
    grads[0] = grads[0] + (d_rpre / L).unsqueeze(1);
  }
  if (p_first.has_value()) d_eta = product_grads[9];
  grads.insert(grads.end(), {d_phi, d_eta_phi, d_psi, d_eta, d_wm});
  grads.insert(grads.end(), {product_grads[6], product_grads[5], product_grads[8], product_grads[7]});
  return grads;
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(sb3_spikeplastic_fast, m) {
  m.def(
      "srm_interval_forward(Tensor x, Tensor h1, Tensor h2, Tensor ref_h1, Tensor ref_h2, Tensor W, Tensor? alpha, "
      "Tensor? E, Tensor? phi, Tensor? eta, Tensor? eta_phi, Tensor? psi, Tensor? w_m, Tensor psp_rows, "
      "Tensor end_rows, bool filter_first, float d, float kappa, float theta, float width, float scale, "
      "float e_max, bool oja, int modulation, bool need_surrogate, bool carry_state) -> Tensor[]");
  m.def(
      "srm_interval_deferred_forward(Tensor x, Tensor h1, Tensor h2, Tensor ref_h1, Tensor ref_h2, Tensor W, "
      "Tensor alpha, Tensor E, Tensor? p_first, Tensor? q_first, Tensor? p_second, Tensor? q_second, Tensor? phi, "
      "Tensor eta, Tensor? eta_phi, Tensor? psi, Tensor? w_m, Tensor psp_rows, Tensor end_rows, "
      "bool filter_first, float d, float kappa, float theta, float width, float scale, float e_max, bool oja, "
      "int modulation, bool need_surrogate, bool write_trace, bool carry_state) -> Tensor[]");
  m.def(
      "srm_interval_deferred_backward(Tensor? d_spikes, Tensor? d_h1, Tensor? d_h2, Tensor? d_r_pre, "
      "Tensor? d_r_post, Tensor? d_E_t, Tensor? d_new_phi, Tensor? d_p, Tensor? d_q, Tensor product_in, "
      "Tensor carried, Tensor W, Tensor alpha, Tensor E, Tensor? p_first, Tensor? q_first, Tensor? p_second, "
      "Tensor? q_second, Tensor surrogate, Tensor p, Tensor pre, Tensor? m, Tensor r_pre, Tensor r_post, "
      "Tensor? phi, Tensor eta, "
      "Tensor? eta_phi, Tensor? psi, Tensor? w_m, Tensor psp_rows, Tensor end_rows, bool filter_first, "
      "bool need_rows, float e_max, bool oja, int modulation, bool write_trace) -> Tensor[]");
  m.def(
      "srm_interval_backward(Tensor? d_spikes, Tensor? d_h1, Tensor? d_h2, Tensor? d_r_pre, Tensor? d_r_post, "
      "Tensor? d_new_E, Tensor? d_new_phi, Tensor product_in, Tensor carried, Tensor W, Tensor? alpha, Tensor? E, "
      "Tensor surrogate, "
      "Tensor p, Tensor pre, Tensor? m, Tensor r_pre, Tensor r_post, Tensor? phi, Tensor? eta, Tensor? eta_phi, "
      "Tensor? psi, Tensor? w_m, Tensor psp_rows, Tensor end_rows, bool filter_first, bool need_rows, "
      "float e_max, bool oja, int modulation) -> Tensor[]");
}

TORCH_LIBRARY_IMPL(sb3_spikeplastic_fast, CPU, m) {
  m.impl("srm_interval_forward", &srm_interval_forward);
  m.impl("srm_interval_backward", &srm_interval_backward);
  m.impl("srm_interval_deferred_forward", &srm_interval_deferred_forward);
  m.impl("srm_interval_deferred_backward", &srm_interval_deferred_backward);
}
