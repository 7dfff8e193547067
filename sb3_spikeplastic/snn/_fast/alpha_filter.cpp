// The alpha filter over an interval by its recurrence (neurons.alpha_filter_step), the CPU form of the operator
// product M [Z; a; b] of neurons.alpha_filter_operator and of its transpose:
//
//     k_t = H2_{t-1} + H1_{t-1},  H2_t = d k_t,  H1_t = d H1_{t-1} + z_t,  psp_t = g k_t
//
// with g = c d, from (H1, H2) = (a, b), and the end state (H1, H2) after the last step. Per value and step it costs
// four operations where the operator costs L + 2 multiply-adds, so a layer can filter its n_out-wide product instead
// of its n_in-wide spikes, and multiply the spikes themselves (spike_product.h). The adjoint runs backwards with
// (G1, G2) the gradients of (H1_t, H2_t), from the end state's:
//
//     dk_t = g dpsp_t + d G2,  dz_t = G1,  then  G1 = dk_t + d G1,  G2 = dk_t
//
// leaving (da, db) = (G1, G2). Both return the rows and the state apart (each contiguous, as the product takes them).

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "denormal_mode.h"
#include "kernels.h"

#include <algorithm>

namespace {

// Columns filtered together: their two state rows stay in L1 (and mostly in registers) over the interval.
constexpr int64_t kColumns = 64;

// The operands with contiguous rows (views of them as they come, a copy otherwise): rows (B, L, n), state (B, n).
at::Tensor with_unit_stride(const at::Tensor& t) { return t.defined() && t.stride(-1) != 1 ? t.contiguous() : t; }

void check_rows(const at::Tensor& rows, const at::Tensor& a, const at::Tensor& b, const char* what) {
  TORCH_CHECK(rows.dim() == 3 && rows.device().is_cpu(), what, ": rows (B, L, n) on the CPU");
  for (const at::Tensor* state : {&a, &b}) {
    if (!state->defined()) continue;
    TORCH_CHECK(state->dim() == 2 && state->size(0) == rows.size(0) && state->size(1) == rows.size(2) &&
                    state->scalar_type() == rows.scalar_type() && state->device().is_cpu(),
                what, ": state rows (B, n) of the rows' dtype");
  }
}

// block(e, j, width) for every environment e and each block of kColumns columns from j, split over torch's threads.
template <typename Block>
void for_column_blocks(int64_t B, int64_t n, const Block& block) {
  const CallerDenormalMode mode;
  at::parallel_for(0, B, 1, [&](int64_t begin, int64_t stop) {
    const DenormalModeScope denormals(mode);
    for (int64_t e = begin; e < stop; ++e) {
      for (int64_t j = 0; j < n; j += kColumns) block(e, j, std::min(kColumns, n - j));
    }
  });
}

// The state row of environment e from column j, or nullptr for an undefined state (zero).
template <typename scalar_t>
const scalar_t* state_at(const at::Tensor& state, int64_t e, int64_t j) {
  return state.defined() ? state.const_data_ptr<scalar_t>() + e * state.stride(0) + j : nullptr;
}

// A state row (undefined: zero) of a block of width columns, into h.
template <typename scalar_t>
void load_state(const scalar_t* state, scalar_t* h, int64_t width) {
  for (int64_t j = 0; j < width; ++j) h[j] = state ? state[j] : scalar_t(0);
}

// The recurrence over a block of columns: the PSP rows into psp when kRows, the rows' sum over the interval into sum
// when kSum, and the end state.
template <typename scalar_t, bool kRows, bool kSum>
void recurrence_block(const scalar_t* z, int64_t z_row, const scalar_t* a, const scalar_t* b, scalar_t* psp,
                      int64_t psp_row, scalar_t* sum, scalar_t* end_a, scalar_t* end_b, int64_t L, int64_t width,
                      scalar_t d, scalar_t g) {
  scalar_t h1[kColumns], h2[kColumns], s[kColumns];
  load_state(a, h1, width);
  load_state(b, h2, width);
  if constexpr (kSum) std::fill(s, s + width, scalar_t(0));
  for (int64_t t = 0; t < L; ++t) {
    const scalar_t* zt = z + t * z_row;
    scalar_t* pt = kRows ? psp + t * psp_row : nullptr;
#pragma omp simd
    for (int64_t j = 0; j < width; ++j) {
      const scalar_t k = h2[j] + h1[j];
      h2[j] = d * k;
      h1[j] = d * h1[j] + zt[j];
      if constexpr (kRows) pt[j] = g * k;
      if constexpr (kSum) s[j] += zt[j];
    }
  }
  std::copy(h1, h1 + width, end_a);
  std::copy(h2, h2 + width, end_b);
  if constexpr (kSum) std::copy(s, s + width, sum);
}

template <typename scalar_t>
void filter_block(const scalar_t* z, int64_t z_row, const scalar_t* a, const scalar_t* b, scalar_t* psp,
                  int64_t psp_row, scalar_t* end_a, scalar_t* end_b, int64_t L, int64_t width, scalar_t d, scalar_t g) {
  recurrence_block<scalar_t, true, false>(z, z_row, a, b, psp, psp_row, nullptr, end_a, end_b, L, width, d, g);
}

template <typename scalar_t>
void adjoint_block(const scalar_t* dpsp, int64_t dpsp_row, const scalar_t* da, const scalar_t* db, scalar_t* dz,
                   int64_t dz_row, scalar_t* d_a, scalar_t* d_b, int64_t L, int64_t width, scalar_t d, scalar_t g) {
  scalar_t g1[kColumns], g2[kColumns];
  load_state(da, g1, width);
  load_state(db, g2, width);
  for (int64_t t = L - 1; t >= 0; --t) {
    const scalar_t* gt = dpsp + t * dpsp_row;
    scalar_t* out = dz + t * dz_row;
#pragma omp simd
    for (int64_t j = 0; j < width; ++j) {
      const scalar_t dk = g * gt[j] + d * g2[j];
      out[j] = g1[j];
      g1[j] = dk + d * g1[j];
      g2[j] = dk;
    }
  }
  std::copy(g1, g1 + width, d_a);
  std::copy(g2, g2 + width, d_b);
}

// Runs kernel (filter_block or adjoint_block, which take their operands alike) over rows (B, L, n) and a state
// (a, b) -> (out rows (B, L, n), out state (B, 2, n)).
template <template <typename> class Kernel>
std::tuple<at::Tensor, at::Tensor> run_blocks(const at::Tensor& rows_in, const at::Tensor& a_in,
                                              const at::Tensor& b_in, double d, double g, const char* what) {
  check_rows(rows_in, a_in, b_in, what);
  const at::Tensor rows = with_unit_stride(rows_in), a = with_unit_stride(a_in), b = with_unit_stride(b_in);
  const int64_t B = rows.size(0), L = rows.size(1), n = rows.size(2);
  at::Tensor out = at::empty({B, L, n}, rows.options());
  at::Tensor state = at::empty({B, 2, n}, rows.options());
  AT_DISPATCH_FLOATING_TYPES(rows.scalar_type(), "alpha_filter", [&] {
    const scalar_t* in = rows.const_data_ptr<scalar_t>();
    scalar_t* out_p = out.mutable_data_ptr<scalar_t>();
    scalar_t* state_p = state.mutable_data_ptr<scalar_t>();
    for_column_blocks(B, n, [&](int64_t e, int64_t j, int64_t width) {
      Kernel<scalar_t>::run(in + e * rows.stride(0) + j, rows.stride(1), state_at<scalar_t>(a, e, j),
                            state_at<scalar_t>(b, e, j), out_p + e * L * n + j, n, state_p + e * 2 * n + j,
                            state_p + (e * 2 + 1) * n + j, L, width, scalar_t(d), scalar_t(g));
    });
  });
  return {out, state};
}

template <typename scalar_t>
struct Filter {
  static constexpr auto run = filter_block<scalar_t>;
};
template <typename scalar_t>
struct Adjoint {
  static constexpr auto run = adjoint_block<scalar_t>;
};

}  // namespace

namespace sb3_spikeplastic_fast {

std::tuple<at::Tensor, at::Tensor> alpha_filter_rows(const at::Tensor& rows, const at::Tensor& state_a,
                                                     const at::Tensor& state_b, double d, double g) {
  return run_blocks<Filter>(rows, state_a, state_b, d, g, "alpha_filter_rows");
}

std::tuple<at::Tensor, at::Tensor> alpha_filter_rows_adjoint(const at::Tensor& d_rows, const at::Tensor& d_end_a,
                                                             const at::Tensor& d_end_b, double d, double g) {
  return run_blocks<Adjoint>(d_rows, d_end_a, d_end_b, d, g, "alpha_filter_rows_adjoint");
}

std::tuple<at::Tensor, at::Tensor> alpha_filter_end_and_mean(const at::Tensor& rows_in, const at::Tensor& a_in,
                                                             const at::Tensor& b_in, double d) {
  check_rows(rows_in, a_in, b_in, "alpha_filter_end_and_mean");
  const at::Tensor rows = with_unit_stride(rows_in), a = with_unit_stride(a_in), b = with_unit_stride(b_in);
  const int64_t B = rows.size(0), L = rows.size(1), n = rows.size(2);
  at::Tensor state = at::empty({B, 2, n}, rows.options());
  at::Tensor sum = at::empty({B, n}, rows.options());
  AT_DISPATCH_FLOATING_TYPES(rows.scalar_type(), "alpha_filter_end_and_mean", [&] {
    const scalar_t* in = rows.const_data_ptr<scalar_t>();
    scalar_t* state_p = state.mutable_data_ptr<scalar_t>();
    scalar_t* sum_p = sum.mutable_data_ptr<scalar_t>();
    for_column_blocks(B, n, [&](int64_t e, int64_t j, int64_t width) {
      // the end state alone (no PSP rows), and the spikes' sum, in the same pass: a layer that multiplies its
      // spikes before filtering needs only these of its input (its next state and r_pre)
      recurrence_block<scalar_t, false, true>(in + e * rows.stride(0) + j, rows.stride(1),
                                              state_at<scalar_t>(a, e, j), state_at<scalar_t>(b, e, j), nullptr, 0,
                                              sum_p + e * n + j, state_p + e * 2 * n + j,
                                              state_p + (e * 2 + 1) * n + j, L, width, scalar_t(d), scalar_t(0));
    });
  });
  // the mean as ATen's mean computes it from the sum: divided by the length
  return {state, sum.div_(L)};
}

}  // namespace sb3_spikeplastic_fast

TORCH_LIBRARY_FRAGMENT(sb3_spikeplastic_fast, m) {
  m.def("alpha_filter_rows(Tensor z, Tensor? a, Tensor? b, float d, float g) -> (Tensor psp, Tensor end)");
  m.def("alpha_filter_rows_adjoint(Tensor dpsp, Tensor? da, Tensor? db, float d, float g) -> (Tensor z, Tensor state)");
  m.def("alpha_filter_end_and_mean(Tensor z, Tensor? a, Tensor? b, float d) -> (Tensor end, Tensor mean)");
}

TORCH_LIBRARY_IMPL(sb3_spikeplastic_fast, CPU, m) {
  m.impl("alpha_filter_rows", [](const at::Tensor& z, const std::optional<at::Tensor>& a,
                                 const std::optional<at::Tensor>& b, double d, double g) {
    return sb3_spikeplastic_fast::alpha_filter_rows(z, a.value_or(at::Tensor()), b.value_or(at::Tensor()), d, g);
  });
  m.impl("alpha_filter_rows_adjoint", [](const at::Tensor& dpsp, const std::optional<at::Tensor>& da,
                                         const std::optional<at::Tensor>& db, double d, double g) {
    return sb3_spikeplastic_fast::alpha_filter_rows_adjoint(dpsp, da.value_or(at::Tensor()),
                                                            db.value_or(at::Tensor()), d, g);
  });
  m.impl("alpha_filter_end_and_mean", [](const at::Tensor& z, const std::optional<at::Tensor>& a,
                                         const std::optional<at::Tensor>& b, double d) {
    return sb3_spikeplastic_fast::alpha_filter_end_and_mean(z, a.value_or(at::Tensor()), b.value_or(at::Tensor()), d);
  });
}
