// One interval of a plastic SRM layer, forward and backward, each as one op (the CPU fast path of
// sb3_spikeplastic.snn.layers.PlasticSRMLayer; the eager step is sb3_spikeplastic.snn.functional.interval_step). The
// forward pass runs the same ATen ops and kernels as the eager step, in the same order but for the filter (below):
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
//
// Each op takes its tensors as one Tensor?[] (IntervalInputs; the backward ops also the gradients of the outputs,
// IntervalOutputs, and what the forward op kept for them, IntervalResiduals), the layer's constants and the rule's
// form as the schema's named scalars (IntervalConstants, RuleForm), and returns named structs as Tensor[]; each
// struct's fields() (op_fields.h) is the only place on this side that orders its tensors, and the op entries at the
// end of this file the only place that builds the structs from the schema's arguments.


#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "denormal_mode.h"
#include "kernels.h"
#include "op_fields.h"

#include <functional>
#include <optional>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

namespace {

using sb3_spikeplastic_fast::ProductGradients;
using sb3_spikeplastic_fast::TensorFields;

// Modulation forms of the rule terms (plasticity.MODULATION_FORMS, 0 for an unmodulated rule).
constexpr int64_t kUnmodulated = 0, kTanh = 2;

// How a built-in rule's trace update is computed (plasticity.compiled_form, interval.RuleForm on the Python side):
// the Oja forms subtract the trace's prediction E pre, the BCM forms take the presynaptic term and sliding threshold,
// the modulated ones M = W_m r_post (1) or tanh(W_m r_post) (2). A layer whose op does not update the trace (no eta)
// passes the default.
struct RuleForm {
  bool oja = false;
  bool bcm = false;
  int64_t modulation = kUnmodulated;
};

// What a layer's intervals of one length share (cached per layer, length, dtype and device): the alpha-filter
// operator's PSP rows (L, L + 2) and end-state rows (2, L + 2) (the op reads the filter's recurrence constants off
// them), whether the layer filters its spikes before the product (n_in <= n_out), the spike loop's constants
// (neurons.spike_constants), the trace bound, and whether the carried PSP state is multiplied beside the spikes
// (layers.PlasticSRMLayer.carries_state).
struct IntervalConstants {
  at::Tensor psp_rows, end_rows;
  bool filter_first = false;
  double d = 0, kappa = 0, theta = 0, width = 0, scale = 0;
  double e_max = 0;
  bool carry_state = false;
};

// The ops' tensors, undefined where absent: the presynaptic spikes x (B, L, n_in); the layer's state: PSP filter
// (h1, h2) and refractory filter (ref_h1, ref_h2), the trace E (plastic layers), the BCM threshold phi, the pending
// updates (p, q) of the deferred form, oldest first; the parameters: W, alpha (plastic layers) and the rule's eta
// (a built-in rule's update), eta_phi and psi (BCM), W_m (modulated).
struct IntervalInputs {
  static constexpr const char* kName = "IntervalInputs";
  at::Tensor x, h1, h2, ref_h1, ref_h2, trace, phi, p_first, q_first, p_second, q_second, weight, alpha, eta, eta_phi,
      psi, w_m;

  static const TensorFields<IntervalInputs>& fields() {
    static const TensorFields<IntervalInputs> list = {
        {"x", &IntervalInputs::x},
        {"h1", &IntervalInputs::h1},
        {"h2", &IntervalInputs::h2},
        {"ref_h1", &IntervalInputs::ref_h1},
        {"ref_h2", &IntervalInputs::ref_h2},
        {"trace", &IntervalInputs::trace},
        {"phi", &IntervalInputs::phi},
        {"p_first", &IntervalInputs::p_first},
        {"q_first", &IntervalInputs::q_first},
        {"p_second", &IntervalInputs::p_second},
        {"q_second", &IntervalInputs::q_second},
        {"weight", &IntervalInputs::weight},
        {"alpha", &IntervalInputs::alpha},
        {"eta", &IntervalInputs::eta},
        {"eta_phi", &IntervalInputs::eta_phi},
        {"psi", &IntervalInputs::psi},
        {"w_m", &IntervalInputs::w_m},
    };
    return list;
  }
};

// The gradient of each input, named as the input; undefined for an input that was not given or gets no gradient (the
// refractory state; x, h1 and h2 unless need_rows).
struct IntervalGradients : IntervalInputs {
  static constexpr const char* kName = "IntervalGradients";
};

// What an interval produced: its spikes and membrane (B, L, n_out), PSP and refractory states, rates r_pre (B, n_in)
// and r_post (B, n_out); the updated trace E' and BCM threshold phi' where the op updated them (the deferred form:
// the trace it used, where it wrote it out); the deferred form's own update (p_next, q_next) for the next interval.
// The backward ops take their gradients in the same struct (undefined where the loss does not reach an output).
struct IntervalOutputs {
  static constexpr const char* kName = "IntervalOutputs";
  at::Tensor spikes, membrane, h1, h2, ref_h1, ref_h2, r_pre, r_post, trace, phi, p_next, q_next;

  static const TensorFields<IntervalOutputs>& fields() {
    static const TensorFields<IntervalOutputs> list = {
        {"spikes", &IntervalOutputs::spikes},
        {"membrane", &IntervalOutputs::membrane},
        {"h1", &IntervalOutputs::h1},
        {"h2", &IntervalOutputs::h2},
        {"ref_h1", &IntervalOutputs::ref_h1},
        {"ref_h2", &IntervalOutputs::ref_h2},
        {"r_pre", &IntervalOutputs::r_pre},
        {"r_post", &IntervalOutputs::r_post},
        {"trace", &IntervalOutputs::trace},
        {"phi", &IntervalOutputs::phi},
        {"p_next", &IntervalOutputs::p_next},
        {"q_next", &IntervalOutputs::q_next},
    };
    return list;
  }
};

// What the backward pass needs from the forward pass besides the inputs: the product's input rows (the filtered or
// raw spikes, with the carried PSP state unless carried apart), the carried rows (B, 2, n_in) when the product took
// them apart, the surrogate gradient of the membrane (empty unless need_surrogate), the trace step's p (post - [E pre]
// or post), pre and the modulatory signal M (modulated rules), and the rates.
struct IntervalResiduals {
  static constexpr const char* kName = "IntervalResiduals";
  at::Tensor product_in, carried, surrogate, p, pre, m, r_pre, r_post;

  static const TensorFields<IntervalResiduals>& fields() {
    static const TensorFields<IntervalResiduals> list = {
        {"product_in", &IntervalResiduals::product_in},
        {"carried", &IntervalResiduals::carried},
        {"surrogate", &IntervalResiduals::surrogate},
        {"p", &IntervalResiduals::p},
        {"pre", &IntervalResiduals::pre},
        {"m", &IntervalResiduals::m},
        {"r_pre", &IntervalResiduals::r_pre},
        {"r_post", &IntervalResiduals::r_post},
    };
    return list;
  }
};

// The product of rows x and, when given, of the rows carried beside them: (x W_eff^T, carried W_eff^T or undefined).
std::pair<at::Tensor, at::Tensor> product(const at::Tensor& x, const at::Tensor& carried, const IntervalInputs& in) {
  // a static layer's rows come whole (interval_forward)
  if (!in.alpha.defined()) return {at::matmul(x, in.weight.t()), at::Tensor()};
  auto [y, yc] = sb3_spikeplastic_fast::plastic_linear_forward(x, in.weight, in.alpha, in.trace, carried);
  return {y, carried.defined() ? yc : at::Tensor()};
}

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

// dX (undefined unless need_x), dW, and for a plastic layer dalpha, dE and dC (undefined unless need_x and carried
// rows are given).
ProductGradients product_backward(const at::Tensor& grad, const at::Tensor& grad_c, const at::Tensor& x,
                                  const at::Tensor& carried, const IntervalInputs& in, bool need_x,
                                  const at::Tensor& dE_init, const RowFill& fill) {
  if (fill) fill_rows_in_parallel(fill, grad.size(0));
  if (!in.alpha.defined()) {
    ProductGradients g;
    g.dW = at::mm(grad.reshape({-1, grad.size(-1)}).t(), x.reshape({-1, x.size(-1)}));
    if (need_x) g.dX = at::matmul(grad, in.weight);
    return g;
  }
  return sb3_spikeplastic_fast::plastic_linear_backward(grad, grad_c, x, in.weight, in.alpha, in.trace, carried,
                                                        need_x, dE_init);
}

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

// The product P of the interval's rows: (rows, carried rows or undefined) -> (P of rows, P of the carried rows or
// undefined). With carries (a plastic layer whose product takes its spikes, with many spike rows:
// layers.PlasticSRMLayer.carries_state), the carried PSP state [h1; h2] is multiplied beside the spikes in the pass
// that builds the efficacy, so that the spikes are not copied into one block of L + 2 rows with it (and stay binary
// for the spike products); the backward pass then takes x as the product's input and the carried rows apart.
using Projection = std::function<std::pair<at::Tensor, at::Tensor>(const at::Tensor&, const at::Tensor&)>;

// The alpha filter's recurrence constants (d, g = c d) as its operator holds them (neurons.alpha_filter_matrices):
// d is v1[L - 2] (d^L itself for L = 1), g is g2[0].
std::pair<double, double> filter_constants(const IntervalConstants& c) {
  const int64_t L = c.psp_rows.size(0);
  const auto entry = [](const at::Tensor& m, int64_t i, int64_t j) {
    return AT_DISPATCH_FLOATING_TYPES(m.scalar_type(), "filter_constants", [&] {
      return static_cast<double>(m.const_data_ptr<scalar_t>()[i * m.stride(0) + j * m.stride(1)]);
    });
  };
  return {entry(c.end_rows, 0, L >= 2 ? L - 2 : L), entry(c.psp_rows, 0, L + 1)};
}

// The interval's input rates r_pre = mean_t x and, for a layer that multiplies its spikes before it filters, the
// PSP state at the interval's end (the filter's recurrence over x from (h1, h2)), both from one pass over x; end is
// undefined for a layer that filters first (its filter's pass gives it).
struct InputPass {
  at::Tensor r_pre, end;
};

InputPass input_pass(const IntervalInputs& in, const IntervalConstants& c) {
  const at::Tensor& x = in.x;
  TORCH_CHECK(x.dim() == 3 && c.psp_rows.dim() == 2 && c.psp_rows.size(0) == x.size(1) &&
                  c.psp_rows.size(1) == x.size(1) + 2 && c.end_rows.dim() == 2 && c.end_rows.size(0) == 2 &&
                  c.end_rows.size(1) == x.size(1) + 2,
              "srm_interval: spikes (B, L, n_in) and the filter operator's (L, L + 2) and (2, L + 2) rows");
  const at::NoGradGuard no_grad;
  if (c.filter_first) return {x.mean(1), at::Tensor()};
  auto [end, r_pre] = sb3_spikeplastic_fast::alpha_filter_end_and_mean(x, in.h1, in.h2, filter_constants(c).first);
  return {r_pre, end};
}

// The interval without the trace update: the outputs spikes ... r_post, and the residuals product_in, carried,
// surrogate, r_pre and r_post.
std::pair<IntervalOutputs, IntervalResiduals> interval_forward(const IntervalInputs& in, const Projection& project,
                                                               bool carries, const IntervalConstants& c,
                                                               bool need_surrogate, const InputPass& pass) {
  const at::NoGradGuard no_grad;
  const at::Tensor &x = in.x, &h1 = in.h1, &h2 = in.h2;
  const int64_t L = x.size(1);
  const auto [psp_d, psp_g] = filter_constants(c);
  at::Tensor product_in, synaptic, end = pass.end, carried;
  if (c.filter_first) {
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
      synaptic, in.ref_h1, in.ref_h2, c.d, c.kappa, c.theta, c.width, c.scale, need_surrogate);
  IntervalOutputs out;
  out.spikes = spikes;
  out.membrane = membrane;
  out.h1 = end.select(1, 0);
  out.h2 = end.select(1, 1);
  out.ref_h1 = rh1;
  out.ref_h2 = rh2;
  out.r_pre = pass.r_pre;
  out.r_post = r_post;
  IntervalResiduals res;
  res.product_in = product_in;
  res.carried = carried;
  res.surrogate = surrogate;
  res.r_pre = pass.r_pre;
  res.r_post = r_post;
  return {out, res};
}

// The product's backward pass: (dL/dP of the rows, of the carried rows (undefined without), need_rows, fill) -> its
// gradients
using ProjectionBackward =
    std::function<ProductGradients(const at::Tensor&, const at::Tensor&, bool, const RowFill&)>;

// The interval's backward pass without the trace update's: sets g.x, g.h1, g.h2 (undefined unless need_rows),
// g.weight, and for a plastic layer g.alpha and g.trace (the product's dE, which the projection's dE_init may have
// started from the trace update's). d.spikes, d.h1 and d.h2 are the outputs' gradients, undefined ones zero.
void interval_backward(const IntervalOutputs& d, const at::Tensor& d_r_pre, const at::Tensor& d_r_post,
                       const IntervalResiduals& res, const ProjectionBackward& project_backward,
                       const IntervalConstants& c, bool need_rows, IntervalGradients& g) {
  const at::NoGradGuard no_grad;
  const int64_t L = res.surrogate.size(1);
  const SynapticGradient synaptic(d.spikes, d_r_post, res.surrogate);
  const auto [psp_d, psp_g] = filter_constants(c);
  const at::Tensor like = res.product_in.select(1, 0);  // (B, n_in), the PSP state's shape
  at::Tensor d_x, d_state;                              // (B, L, n_in) and (B, 2, n_in) when need_rows
  ProductGradients pg;
  if (c.filter_first) {
    // each environment's dL/dsyn written just before its product reads it
    pg = project_backward(synaptic.output(), at::Tensor(), need_rows,
                          [&](int64_t b0, int64_t n) { synaptic.fill(b0, n); });
    if (need_rows) {
      std::tie(d_x, d_state) = sb3_spikeplastic_fast::alpha_filter_rows_adjoint(pg.dX, d.h1, d.h2, psp_d, psp_g);
    }
  } else {
    // (B, L, n_out) and (B, 2, n_out)
    const auto [d_product, d_product_state] = sb3_spikeplastic_fast::alpha_filter_rows_adjoint(
        synaptic.fill_all(), at::Tensor(), at::Tensor(), psp_d, psp_g);
    const bool carries = res.carried.defined();
    if (carries) {
      pg = project_backward(d_product, d_product_state, need_rows, {});
    } else {
      pg = project_backward(at::cat({d_product, d_product_state}, 1), at::Tensor(), need_rows, {});
    }
    if (need_rows) {
      const at::Tensor d_end = at::stack({or_zeros(d.h1, like), or_zeros(d.h2, like)}, 1);
      d_x = pg.dX.narrow(1, 0, L) + at::matmul(c.end_rows.narrow(1, 0, L).t(), d_end);
      d_state = (carries ? pg.dC : pg.dX.narrow(1, L, 2)) + at::matmul(c.end_rows.narrow(1, L, 2).t(), d_end);
    }
  }
  if (need_rows) {
    if (d_r_pre.defined()) d_x = d_x + (d_r_pre / L).unsqueeze(1);
    g.x = d_x;
    g.h1 = d_state.select(1, 0);
    g.h2 = d_state.select(1, 1);
  }
  g.weight = pg.dW;
  g.alpha = pg.dalpha;
  g.trace = pg.dE;
}

// The rule's presynaptic term (plasticity.bcm_presynaptic_term and bcm_threshold_update with phi, else r_pre) ->
// (pre, phi' or undefined).
std::pair<at::Tensor, at::Tensor> presynaptic_term(const at::Tensor& r_pre, const IntervalInputs& in,
                                                   const RuleForm& rule) {
  if (!rule.bcm) return {r_pre, at::Tensor()};
  return {r_pre * (r_pre - (in.phi + in.psi)), at::rsub(in.eta_phi, 1) * in.phi + in.eta_phi * r_pre};
}

// The rule's postsynaptic term (plasticity.modulatory_signal: M * r_post with M = W_m r_post or its tanh, else
// r_post) -> (post, M or undefined).
std::pair<at::Tensor, at::Tensor> postsynaptic_term(const at::Tensor& r_post, const IntervalInputs& in,
                                                    const RuleForm& rule) {
  if (rule.modulation == kUnmodulated) return {r_post, at::Tensor()};
  at::Tensor m = at::matmul(r_post, in.w_m.t());
  if (rule.modulation == kTanh) m = at::tanh(m);
  return {m * r_post, m};
}

// The postsynaptic term's backward pass: adds to d_rpost, sets g.w_m (unchanged without modulation).
void postsynaptic_backward(const at::Tensor& d_post, const IntervalResiduals& res, const IntervalInputs& in,
                           const RuleForm& rule, at::Tensor& d_rpost, IntervalGradients& g) {
  if (rule.modulation == kUnmodulated) {
    d_rpost = plus(d_rpost, d_post);
    return;
  }
  at::Tensor d_m = d_post * res.r_post;
  d_rpost = plus(d_rpost, d_post * res.m);
  if (rule.modulation == kTanh) d_m = d_m * (1 - res.m * res.m);
  g.w_m = at::mm(d_m.t(), res.r_post);
  d_rpost = d_rpost + at::mm(d_m, in.w_m);
}

// The presynaptic term's backward pass, with d_new_phi the gradient of phi': adds to d_rpre, sets g.phi, g.psi and
// g.eta_phi (unchanged unless BCM).
void presynaptic_backward(const at::Tensor& d_pre, const at::Tensor& d_new_phi, const IntervalResiduals& res,
                          const IntervalInputs& in, const RuleForm& rule, at::Tensor& d_rpre, IntervalGradients& g) {
  if (!rule.bcm) {
    d_rpre = plus(d_rpre, d_pre);
    return;
  }
  const at::Tensor& r_pre = res.r_pre;
  const at::Tensor d_new_phi_or_zero = or_zeros(d_new_phi, in.phi);
  const at::Tensor d_threshold = -(d_pre * r_pre);  // of phi + psi
  d_rpre = plus(d_rpre, d_pre * (2 * r_pre - (in.phi + in.psi))) + d_new_phi_or_zero * in.eta_phi;
  g.phi = d_threshold + d_new_phi_or_zero * at::rsub(in.eta_phi, 1);
  g.psi = d_threshold.sum(0);
  g.eta_phi = (d_new_phi_or_zero * (r_pre - in.phi)).sum();
}

void check_rule(const IntervalInputs& in, const RuleForm& rule) {
  TORCH_CHECK(in.alpha.defined() == in.trace.defined(), "srm_interval: alpha and E come together");
  TORCH_CHECK(!in.eta.defined() || in.trace.defined(), "srm_interval: a trace update needs E");
  TORCH_CHECK(in.phi.defined() == rule.bcm && in.eta_phi.defined() == rule.bcm && in.psi.defined() == rule.bcm,
              "srm_interval: phi, eta_phi and psi with a BCM rule form, and only then");
  TORCH_CHECK(rule.modulation >= kUnmodulated && rule.modulation <= kTanh &&
                  (rule.modulation != kUnmodulated) == in.w_m.defined(),
              "srm_interval: W_m with a modulation form 1 (linear) or 2 (tanh), or neither");
}

// The interval, then (when eta is given: a built-in rule's layer) the trace update: the outputs up to E' and phi'
// (undefined unless BCM), the residuals (p, pre and M undefined without a trace update; M also unless modulated).
std::pair<IntervalOutputs, IntervalResiduals> interval_with_update(const IntervalInputs& in,
                                                                   const IntervalConstants& c, const RuleForm& rule,
                                                                   bool need_surrogate) {
  check_rule(in, rule);
  TORCH_CHECK(!in.p_first.defined() && !in.p_second.defined(),
              "srm_interval_forward: pending updates are srm_interval_deferred_forward's");
  const at::NoGradGuard no_grad;
  auto [out, res] = interval_forward(
      in, [&](const at::Tensor& rows, const at::Tensor& carried) { return product(rows, carried, in); },
      c.carry_state && in.alpha.defined(), c, need_surrogate, input_pass(in, c));
  if (in.eta.defined()) {
    at::Tensor post;
    std::tie(res.pre, out.phi) = presynaptic_term(out.r_pre, in, rule);
    std::tie(post, res.m) = postsynaptic_term(out.r_post, in, rule);
    std::tie(out.trace, res.p) = sb3_spikeplastic_fast::trace_step_forward(in.trace, post, res.pre,
                                                                           in.eta.item<double>(), c.e_max, rule.oja);
  }
  return {out, res};
}

// The backward pass of interval_with_update; d holds the gradients of its outputs.
IntervalGradients interval_with_update_backward(const IntervalOutputs& d, const IntervalResiduals& res,
                                                const IntervalInputs& in, const IntervalConstants& c,
                                                const RuleForm& rule, bool need_rows) {
  const at::NoGradGuard no_grad;
  IntervalGradients g;
  at::Tensor d_rpost = d.r_post, d_rpre = d.r_pre, dE_trace;
  if (in.eta.defined()) {
    at::Tensor d_post, d_pre;
    std::tie(dE_trace, d_post, d_pre, g.eta) = sb3_spikeplastic_fast::trace_step_backward(
        or_zeros(d.trace, in.trace), in.trace, res.p, res.pre, in.eta.item<double>(), c.e_max, rule.oja);
    postsynaptic_backward(d_post, res, in, rule, d_rpost, g);
    presynaptic_backward(d_pre, d.phi, res, in, rule, d_rpre, g);
  }
  interval_backward(
      d, d_rpre, d_rpost, res,
      [&](const at::Tensor& grad, const at::Tensor& grad_c, bool need_x, const RowFill& fill) {
        return product_backward(grad, grad_c, res.product_in, res.carried, in, need_x, dE_trace, fill);
      },
      c, need_rows, g);
  return g;
}

// The deferred form (a built-in rule's layer inside a training sequence, layers.PlasticSRMLayer with
// defer_update): the previous intervals' trace updates, clamp((1 - eta) E + (eta p) (x) q) for each pending (p, q),
// oldest first, run in this interval's pass over E (plastic_linear_deferred_forward), and this interval's update is
// returned as (p_next, q_next = pre) for the next. Each interval then reads its trace once forward and once backward,
// where the update in its own pass reads it again. Without a pending update E is the trace itself. The trace the
// interval used is written out (the output trace) only when write_trace: a sequence keeps every other trace and
// recomputes the others from the one before and the two updates since. The values are those of interval_with_update
// bit for bit.
std::pair<IntervalOutputs, IntervalResiduals> deferred_interval(const IntervalInputs& in, const IntervalConstants& c,
                                                                const RuleForm& rule, bool need_surrogate,
                                                                bool write_trace) {
  check_rule(in, rule);
  TORCH_CHECK(in.eta.defined(), "srm_interval_deferred_forward: a built-in rule's layer (eta given)");
  const at::NoGradGuard no_grad;
  const double eta_value = in.eta.item<double>();
  const InputPass pass = input_pass(in, c);
  at::Tensor pre, new_phi, post, m;  // not structured bindings: the lambda below captures pre (C++17)
  std::tie(pre, new_phi) = presynaptic_term(pass.r_pre, in, rule);
  at::Tensor E_t, r;
  auto [out, res] = interval_forward(
      in,
      [&](const at::Tensor& rows, const at::Tensor& carried) {
        const sb3_spikeplastic_fast::DeferredProduct y = sb3_spikeplastic_fast::plastic_linear_deferred_forward(
            rows, in.weight, in.alpha, in.trace, carried, in.p_first, in.q_first, in.p_second, in.q_second,
            rule.oja ? pre : at::Tensor(), eta_value, c.e_max, write_trace);
        E_t = y.E_t;
        r = y.r;
        return std::make_pair(y.Y, carried.defined() ? y.Yc : at::Tensor());
      },
      c.carry_state, c, need_surrogate, pass);
  std::tie(post, m) = postsynaptic_term(out.r_post, in, rule);
  const at::Tensor p = rule.oja ? post - r : post;
  if (E_t.numel() > 0) out.trace = E_t;  // empty unless written
  out.phi = new_phi;
  // p and q as outputs of their own: without Oja's term or BCM's they are r_post and r_pre themselves
  out.p_next = p.is_same(out.r_post) ? p.clone() : p;
  out.q_next = pre.is_same(out.r_pre) ? pre.clone() : pre;
  res.p = p;
  res.pre = pre;
  res.m = m;
  return {out, res};
}

// The backward pass of deferred_interval. d.trace is the gradient of the trace the interval passed on (E_t when
// written, else E itself), d.p_next and d.q_next those of the returned update; g.trace is dL/dE of the input trace,
// g.p_first ... g.q_second those of the pending updates.
IntervalGradients deferred_interval_backward(const IntervalOutputs& d, const IntervalResiduals& res,
                                             const IntervalInputs& in, const IntervalConstants& c,
                                             const RuleForm& rule, bool need_rows, bool write_trace) {
  const at::NoGradGuard no_grad;
  const double eta_value = in.eta.item<double>();
  // p = post - r (Oja) or post
  const at::Tensor d_p = d.p_next.defined() ? d.p_next : at::zeros_like(res.p);
  IntervalGradients g;
  g.eta = at::zeros({}, in.weight.options());
  at::Tensor d_rpost = d.r_post, d_rpre = d.r_pre;
  postsynaptic_backward(d_p, res, in, rule, d_rpost, g);
  sb3_spikeplastic_fast::DeferredProductGradients pg;
  interval_backward(
      d, at::Tensor(), d_rpost, res,
      [&](const at::Tensor& grad, const at::Tensor& grad_c, bool need_x, const RowFill& fill) {
        pg = sb3_spikeplastic_fast::plastic_linear_deferred_backward(
            grad, grad_c, res.product_in, in.weight, in.alpha, in.trace, res.carried, in.p_first, in.q_first,
            in.p_second, in.q_second, rule.oja ? res.pre : at::Tensor(), d.trace, rule.oja ? -d_p : at::Tensor(),
            need_x, eta_value, c.e_max, write_trace, fill);
        ProductGradients product;
        product.dX = pg.dX;
        product.dW = pg.dW;
        product.dalpha = pg.dalpha;
        product.dE = pg.dE;
        product.dC = pg.dC;
        return product;
      },
      c, need_rows, g);
  // dL/dpre: from the next interval's update and from the Oja term's row sums; then the rates (only now: the row
  // sums' gradient comes out of the product's pass)
  at::Tensor d_pre = d.q_next;
  if (rule.oja) d_pre = plus(d_pre, pg.dq);
  if (!d_pre.defined()) d_pre = at::zeros_like(res.pre);
  presynaptic_backward(d_pre, d.phi, res, in, rule, d_rpre, g);
  if (need_rows && d_rpre.defined()) {
    const int64_t L = res.surrogate.size(1);
    g.x = g.x + (d_rpre / L).unsqueeze(1);
  }
  if (in.p_first.defined()) g.eta = pg.deta;
  if (in.p_first.defined()) {
    g.p_first = pg.dp0;
    g.q_first = pg.dq0;
  }
  if (in.p_second.defined()) {
    g.p_second = pg.dp1;
    g.q_second = pg.dq1;
  }
  return g;
}

// The op entries: the one place per op that reads the schema's arguments (TORCH_LIBRARY_FRAGMENT below) into the
// structs above, and writes the structs out.
using TensorList = c10::List<std::optional<at::Tensor>>;
using ForwardResult = std::tuple<std::vector<at::Tensor>, std::vector<at::Tensor>>;

ForwardResult forward_result(const std::pair<IntervalOutputs, IntervalResiduals>& result) {
  return {sb3_spikeplastic_fast::to_list(result.first), sb3_spikeplastic_fast::to_list(result.second)};
}

ForwardResult srm_interval_forward(const TensorList& inputs, const at::Tensor& psp_rows, const at::Tensor& end_rows,
                                   bool filter_first, double d, double kappa, double theta, double width,
                                   double scale, double e_max, bool carry_state, bool oja, bool bcm,
                                   int64_t modulation, bool need_surrogate) {
  const IntervalConstants c{psp_rows, end_rows, filter_first, d, kappa, theta, width, scale, e_max, carry_state};
  const RuleForm rule{oja, bcm, modulation};
  return forward_result(
      interval_with_update(sb3_spikeplastic_fast::from_list<IntervalInputs>(inputs), c, rule, need_surrogate));
}

std::vector<at::Tensor> srm_interval_backward(const TensorList& grad_outputs, const TensorList& residuals,
                                              const TensorList& inputs, const at::Tensor& psp_rows,
                                              const at::Tensor& end_rows, bool filter_first, double d, double kappa,
                                              double theta, double width, double scale, double e_max,
                                              bool carry_state, bool oja, bool bcm, int64_t modulation,
                                              bool need_rows) {
  const IntervalConstants c{psp_rows, end_rows, filter_first, d, kappa, theta, width, scale, e_max, carry_state};
  const RuleForm rule{oja, bcm, modulation};
  const IntervalInputs in = sb3_spikeplastic_fast::from_list<IntervalInputs>(inputs);
  return sb3_spikeplastic_fast::to_list(interval_with_update_backward(
      sb3_spikeplastic_fast::from_list<IntervalOutputs>(grad_outputs),
      sb3_spikeplastic_fast::from_list<IntervalResiduals>(residuals), in, c, rule, need_rows));
}

ForwardResult srm_interval_deferred_forward(const TensorList& inputs, const at::Tensor& psp_rows,
                                            const at::Tensor& end_rows, bool filter_first, double d, double kappa,
                                            double theta, double width, double scale, double e_max, bool carry_state,
                                            bool oja, bool bcm, int64_t modulation, bool need_surrogate,
                                            bool write_trace) {
  const IntervalConstants c{psp_rows, end_rows, filter_first, d, kappa, theta, width, scale, e_max, carry_state};
  const RuleForm rule{oja, bcm, modulation};
  return forward_result(deferred_interval(sb3_spikeplastic_fast::from_list<IntervalInputs>(inputs), c, rule,
                                          need_surrogate, write_trace));
}

std::vector<at::Tensor> srm_interval_deferred_backward(const TensorList& grad_outputs, const TensorList& residuals,
                                                       const TensorList& inputs, const at::Tensor& psp_rows,
                                                       const at::Tensor& end_rows, bool filter_first, double d,
                                                       double kappa, double theta, double width, double scale,
                                                       double e_max, bool carry_state, bool oja, bool bcm,
                                                       int64_t modulation, bool need_rows, bool write_trace) {
  const IntervalConstants c{psp_rows, end_rows, filter_first, d, kappa, theta, width, scale, e_max, carry_state};
  const RuleForm rule{oja, bcm, modulation};
  const IntervalInputs in = sb3_spikeplastic_fast::from_list<IntervalInputs>(inputs);
  return sb3_spikeplastic_fast::to_list(deferred_interval_backward(
      sb3_spikeplastic_fast::from_list<IntervalOutputs>(grad_outputs),
      sb3_spikeplastic_fast::from_list<IntervalResiduals>(residuals), in, c, rule, need_rows, write_trace));
}

// The field names of the struct called name, in the order its tensors travel (for the Python side's test).
std::vector<std::string> srm_interval_fields(std::string name) {
  using sb3_spikeplastic_fast::field_names;
  if (name == IntervalInputs::kName) return field_names<IntervalInputs>();
  if (name == IntervalGradients::kName) return field_names<IntervalGradients>();
  if (name == IntervalOutputs::kName) return field_names<IntervalOutputs>();
  TORCH_CHECK(name == IntervalResiduals::kName, "srm_interval_fields: no struct ", name);
  return field_names<IntervalResiduals>();
}

}  // namespace

// The schemas' scalars after the tensors: IntervalConstants, then RuleForm, in their fields' order.
#define SRM_INTERVAL_CONSTANTS                                                                                  \
  "Tensor psp_rows, Tensor end_rows, bool filter_first, float d, float kappa, float theta, float width, "     \
  "float scale, float e_max, bool carry_state, bool oja, bool bcm, int modulation"

TORCH_LIBRARY_FRAGMENT(sb3_spikeplastic_fast, m) {
  m.def("srm_interval_forward(Tensor?[] inputs, " SRM_INTERVAL_CONSTANTS
        ", bool need_surrogate) -> (Tensor[] outputs, Tensor[] residuals)");
  m.def("srm_interval_backward(Tensor?[] grad_outputs, Tensor?[] residuals, Tensor?[] inputs, " SRM_INTERVAL_CONSTANTS
        ", bool need_rows) -> Tensor[] gradients");
  m.def("srm_interval_deferred_forward(Tensor?[] inputs, " SRM_INTERVAL_CONSTANTS
        ", bool need_surrogate, bool write_trace) -> (Tensor[] outputs, Tensor[] residuals)");
  m.def("srm_interval_deferred_backward(Tensor?[] grad_outputs, Tensor?[] residuals, Tensor?[] inputs, "
        SRM_INTERVAL_CONSTANTS ", bool need_rows, bool write_trace) -> Tensor[] gradients");
  m.def("srm_interval_fields(str name) -> str[]", &srm_interval_fields);
}

TORCH_LIBRARY_IMPL(sb3_spikeplastic_fast, CPU, m) {
  m.impl("srm_interval_forward", &srm_interval_forward);
  m.impl("srm_interval_backward", &srm_interval_backward);
  m.impl("srm_interval_deferred_forward", &srm_interval_deferred_forward);
  m.impl("srm_interval_deferred_backward", &srm_interval_deferred_backward);
}
