// Counter-based Bernoulli spikes (the CPU fast path of sb3_spikeplastic.coding.CounterBernoulli.sample).
//
//     spike[b, t, i] = U(b, t, i) < p[b, i],   U = ((h >> 8) & 0xFFFFFF) * 2^-24,
//     h = hash32(index_hash[t, i] ^ hash32(key[b]))
//
// hash32 is the multiply/xor-shift finaliser of Wellons' "lowbias32". The PyTorch version works on int32 with
// wrapping products and masked arithmetic shifts; uint32 arithmetic here gives the same bits, so the spikes are
// bit-identical. One pass instead of ~12 eager passes over the (batch, steps, n) array.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/core/ScalarType.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>

namespace {

inline uint32_t hash32(uint32_t x) {
  x ^= x >> 16;
  x *= 0x7FEB352Du;
  x ^= x >> 15;
  x *= 0x846CA68Bu;
  x ^= x >> 16;
  return x;
}

template <typename scalar_t>
void spike_row(const uint32_t* __restrict index_hash, const scalar_t* __restrict p, scalar_t* __restrict out,
               uint32_t key_hash, int64_t n) {
  const float scale = 1.0f / 16777216.0f;
#pragma omp simd
  for (int64_t i = 0; i < n; ++i) {
    const uint32_t h = hash32(index_hash[i] ^ key_hash);
    const float u = static_cast<float>((h >> 8) & 0xFFFFFFu) * scale;
    out[i] = static_cast<scalar_t>(u) < p[i] ? scalar_t(1) : scalar_t(0);
  }
}

at::Tensor bernoulli_spikes(const at::Tensor& p_in, const at::Tensor& keys_in, const at::Tensor& index_hash_in) {
  TORCH_CHECK(p_in.dim() == 2 && keys_in.dim() == 1 && index_hash_in.dim() == 2 && keys_in.size(0) == p_in.size(0) &&
                  index_hash_in.size(1) == p_in.size(1),
              "bernoulli_spikes: p (B, n), keys (B,), index_hash (T, n)");
  TORCH_CHECK(keys_in.scalar_type() == at::kInt && index_hash_in.scalar_type() == at::kInt,
              "bernoulli_spikes: int32 keys and index hashes");
  TORCH_CHECK(p_in.scalar_type() == at::kFloat || p_in.scalar_type() == at::kDouble,
              "bernoulli_spikes: float32 or float64 probabilities");
  const at::Tensor p = p_in.contiguous(), keys = keys_in.contiguous(), index_hash = index_hash_in.contiguous();
  const int64_t B = p.size(0), T = index_hash.size(0), n = p.size(1);
  at::Tensor out = at::empty({B, T, n}, p.options());
  const uint32_t* idx = reinterpret_cast<const uint32_t*>(index_hash.data_ptr<int32_t>());
  const uint32_t* key = reinterpret_cast<const uint32_t*>(keys.data_ptr<int32_t>());
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "bernoulli_spikes", [&] {
    const scalar_t* p_p = p.data_ptr<scalar_t>();
    scalar_t* o_p = out.data_ptr<scalar_t>();
    at::parallel_for(0, B * T, std::max<int64_t>(1, 32768 / std::max<int64_t>(n, 1)), [&](int64_t begin, int64_t end) {
      for (int64_t r = begin; r < end; ++r) {
        const int64_t b = r / T, t = r % T;
        spike_row<scalar_t>(idx + t * n, p_p + b * n, o_p + r * n, hash32(key[b]), n);
      }
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(sb3_spikeplastic_fast, m) {
  m.def("bernoulli_spikes(Tensor p, Tensor keys, Tensor index_hash) -> Tensor");
}

TORCH_LIBRARY_IMPL(sb3_spikeplastic_fast, CPU, m) {
  m.impl("bernoulli_spikes", &bernoulli_spikes);
}
