"""A design measurement: the plastic layers' trace update deferred to the next interval's pass over the trace.

Today each plastic layer and interval passes over its trace ``E`` (``B x n_out x n_in``) several times: forward,
once to build the efficacy ``W + alpha * E`` for the product and once for the update
``E' = clamp((1 - eta) E + (eta p) (x) q)``, which needs the interval's output rates and so cannot come first;
backward, once for the update's gradient and once for the product's (``_fast/srm_interval.cpp``). If the update of
interval ``t`` runs at the start of interval ``t + 1`` instead, in the same pass that builds ``t + 1``'s efficacy
(and the Oja term's row sums ``E q``), every interval reads its trace once forward and once backward:

    forward, per row:   E_t = clamp(keep E_{t-1} + ep_{t-1} q_{t-1});  eff = W + alpha E_t;  r = E_t . q_t
                        then Y = X eff^T
    backward, per row:  recompute E_t and the clamp's mask from E_{t-1};  G = dY^T X (before the pass);
                        dE_t = dE_t(next interval) + alpha G - dp q_t;  dW += G;  dalpha += G E_t;  dq_t -= dp E_t;
                        eff over G (for dX);  gx = mask dE_t;  dE_{t-1} = keep gx;  dep_{t-1} = gx . q_{t-1};
                        dq_{t-1} += ep gx;  then dX = dY eff

The rule's vector terms (``p = post - r``, the modulation, BCM) stay as they are; the gradient of ``p`` reaches
interval ``t`` from ``t + 1``'s backward pass, so the product's backward no longer waits for a pass over the trace.
This script times that one-pass kernel pair (compiled here, float32) against the extension's kernels that do the
same work today, at the paper network's plastic layer sizes, batch 32, cycling through 24 distinct sets of data as
a BPTT pass does; it first checks the kernels' values and gradients against eager autograd. The baseline backward
leaves out the ``dE_init`` read of the real op's row pass, so the saving it shows is a lower bound.

    python benchmarks/deferred_trace_update.py --threads 2     # -> benchmarks/results/deferred_trace_update.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from torch.utils.cpp_extension import load_inline

sys.path.insert(0, str(Path(__file__).parent))
from machine import describe_machine  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "deferred_trace_update.json"

SOURCE = r"""
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <vector>

extern "C" void sgemm_(const char*, const char*, const int*, const int*, const int*, const float*, const float*,
                       const int*, const float*, const int*, const float*, float*, const int*);

namespace {

typedef float V __attribute__((vector_size(32)));
typedef int Mask __attribute__((vector_size(32)));

void gemm(char ta, char tb, int m, int n, int k, const float* a, int lda, const float* b, int ldb, float* c, int ldc) {
  const float one = 1, zero = 0;
  sgemm_(&ta, &tb, &m, &n, &k, &one, a, &lda, b, &ldb, &zero, c, &ldc);
}
inline V splat(float x) { return V{x, x, x, x, x, x, x, x}; }
inline V ld(const float* p) { V v; __builtin_memcpy(&v, p, sizeof v); return v; }
inline void st(float* p, V v) { __builtin_memcpy(p, &v, sizeof v); }
inline float lanes(V v) { float s = 0; for (int k = 0; k < 8; ++k) s += v[k]; return s; }
inline float clampf(float x, float lo, float hi) { return x < lo ? lo : (x > hi ? hi : x); }
inline V clampv(V x, V lo, V hi) { return x < lo ? lo : (x > hi ? hi : x); }

}  // namespace

// -> Y (B, R, O), E_t, r = E_t q_t (B, O)
std::vector<at::Tensor> forward(at::Tensor X, at::Tensor W, at::Tensor A, at::Tensor E0, at::Tensor ep,
                                at::Tensor q0, at::Tensor q, double keep_, double e_max) {
  const int64_t B = X.size(0), R = X.size(1), O = W.size(0), I = W.size(1), N = O * I;
  at::Tensor E1 = at::empty_like(E0), Y = at::empty({B, R, O}, X.options()), r = at::empty({B, O}, X.options());
  const float keep = keep_, hi = e_max, lo = -e_max;
  const float *x = X.data_ptr<float>(), *w = W.data_ptr<float>(), *a = A.data_ptr<float>(),
              *e0 = E0.data_ptr<float>(), *ep_p = ep.data_ptr<float>(), *q0_p = q0.data_ptr<float>(),
              *q_p = q.data_ptr<float>();
  float *e1 = E1.data_ptr<float>(), *y = Y.data_ptr<float>(), *r_p = r.data_ptr<float>();
  at::parallel_for(0, B, 1, [&](int64_t begin, int64_t end) {
    std::vector<float> eff(N);
    for (int64_t b = begin; b < end; ++b) {
      const float *Q0 = q0_p + b * I, *Q = q_p + b * I;
      for (int64_t o = 0; o < O; ++o) {
        const float *e = e0 + b * N + o * I, *wr = w + o * I, *ar = a + o * I;
        float *et = e1 + b * N + o * I, *f = eff.data() + o * I;
        const float epo = ep_p[b * O + o];
        const V kv = splat(keep), ev = splat(epo), lov = splat(lo), hiv = splat(hi);
        V acc = splat(0);
        int64_t i = 0;
        for (; i + 8 <= I; i += 8) {
          const V v = clampv(ld(e + i) * kv + ev * ld(Q0 + i), lov, hiv);
          st(et + i, v);
          st(f + i, ld(wr + i) + ld(ar + i) * v);
          acc += v * ld(Q + i);
        }
        float s = lanes(acc);
        for (; i < I; ++i) {
          const float v = clampf(e[i] * keep + epo * Q0[i], lo, hi);
          et[i] = v; f[i] = wr[i] + ar[i] * v; s += v * Q[i];
        }
        r_p[b * O + o] = s;
      }
      gemm('T', 'N', O, R, I, eff.data(), I, x + b * R * I, I, y + b * R * O, O);
    }
  });
  return {Y, E1, r};
}

// -> dX (empty unless need_x), dE_{t-1}, per-thread (dW, dalpha) sums, dq_t, dq_{t-1}, dep_{t-1}
std::vector<at::Tensor> backward(at::Tensor dY, at::Tensor X, at::Tensor W, at::Tensor A, at::Tensor E0,
                                 at::Tensor ep, at::Tensor q0, at::Tensor q, at::Tensor dE1, at::Tensor dp,
                                 bool need_x, double keep_, double e_max) {
  const int64_t B = X.size(0), R = X.size(1), O = W.size(0), I = W.size(1), N = O * I;
  const int64_t threads = at::get_num_threads();
  at::Tensor dE0 = at::empty_like(E0), acc = at::zeros({threads, 2, O, I}, X.options());
  at::Tensor dq = at::zeros({B, I}, X.options()), dq0 = at::zeros({B, I}, X.options());
  at::Tensor dep = at::empty({B, O}, X.options());
  at::Tensor dX = need_x ? at::empty_like(X) : at::empty({0}, X.options());
  const float keep = keep_, hi = e_max, lo = -e_max;
  const float *x = X.data_ptr<float>(), *w = W.data_ptr<float>(), *a = A.data_ptr<float>(),
              *e0 = E0.data_ptr<float>(), *ep_p = ep.data_ptr<float>(), *q0_p = q0.data_ptr<float>(),
              *q_p = q.data_ptr<float>(), *g = dY.data_ptr<float>(), *de1 = dE1.data_ptr<float>(),
              *dp_p = dp.data_ptr<float>();
  float *de0 = dE0.data_ptr<float>(), *acc_p = acc.data_ptr<float>(), *dq_p = dq.data_ptr<float>(),
        *dq0_p = dq0.data_ptr<float>(), *dep_p = dep.data_ptr<float>(), *dx = need_x ? dX.data_ptr<float>() : nullptr;
  at::parallel_for(0, B, 1, [&](int64_t begin, int64_t end) {
    std::vector<float> G(N);
    float* dw = acc_p + at::get_thread_num() * 2 * N;
    float* da = dw + N;
    for (int64_t b = begin; b < end; ++b) {
      gemm('N', 'T', I, O, R, x + b * R * I, I, g + b * R * O, O, G.data(), I);
      const float *Q0 = q0_p + b * I, *Q = q_p + b * I;
      float *DQ = dq_p + b * I, *DQ0 = dq0_p + b * I;
      for (int64_t o = 0; o < O; ++o) {
        const int64_t off = b * N + o * I;
        const float *e = e0 + off, *d1 = de1 + off, *wr = w + o * I, *ar = a + o * I;
        float *d0 = de0 + off, *Gr = G.data() + o * I, *dwr = dw + o * I, *dar = da + o * I;
        const float epo = ep_p[b * O + o], dpo = dp_p[b * O + o];
        const V kv = splat(keep), ev = splat(epo), dv = splat(dpo), lov = splat(lo), hiv = splat(hi);
        V s = splat(0);
        int64_t i = 0;
        for (; i + 8 <= I; i += 8) {
          const V q0v = ld(Q0 + i), qv = ld(Q + i), gv = ld(Gr + i), av = ld(ar + i);
          const V xv = ld(e + i) * kv + ev * q0v;
          const Mask clipped = (xv < lov) | (xv > hiv);
          const V et = clampv(xv, lov, hiv);
          const V total = ld(d1 + i) + av * gv - dv * qv;
          st(dwr + i, ld(dwr + i) + gv);
          st(dar + i, ld(dar + i) + gv * et);
          st(DQ + i, ld(DQ + i) - dv * et);
          st(Gr + i, ld(wr + i) + av * et);
          const V gx = (V)((Mask)total & ~clipped);
          st(d0 + i, kv * gx);
          s += gx * q0v;
          st(DQ0 + i, ld(DQ0 + i) + ev * gx);
        }
        float sum = lanes(s);
        for (; i < I; ++i) {
          const float xv = e[i] * keep + epo * Q0[i];
          const float et = clampf(xv, lo, hi);
          const float total = d1[i] + ar[i] * Gr[i] - dpo * Q[i];
          dwr[i] += Gr[i]; dar[i] += Gr[i] * et; DQ[i] -= dpo * et;
          Gr[i] = wr[i] + ar[i] * et;
          const float gx = (xv < lo || xv > hi) ? 0.f : total;
          d0[i] = keep * gx; sum += gx * Q0[i]; DQ0[i] += epo * gx;
        }
        dep_p[b * O + o] = sum;
      }
      if (need_x) gemm('N', 'N', I, R, O, G.data(), I, g + b * R * O, O, dx + b * R * I, I);
    }
  });
  return {dX, dE0, acc.sum(0), dq, dq0, dep};
}
"""

# (name, n_out, n_in, product rows, whether the product's input needs a gradient): the paper network's input layer
# (600 place cells -> 64, spikes and the two PSP-state rows) and output layer (64 -> 600, filtered spikes)
LAYERS = (("input layer 600 -> 64", 64, 600, 52, False), ("output layer 64 -> 600", 600, 64, 50, True))
KEEP, E_MAX = 0.9, 1.0


def build():
    return load_inline("deferred_trace_update", cpp_sources=SOURCE, functions=["forward", "backward"],
                       extra_cflags=["-O3", "-mavx2", "-fopenmp", "-ffp-contract=off"], extra_ldflags=["-fopenmp"])


def check(ext) -> float:
    """Largest relative error of the kernels' values and gradients against eager autograd (float32)."""
    torch.manual_seed(0)
    B, O, I, R = 3, 24, 40, 7
    X = (torch.rand(B, R, I) < 0.3).float()
    W, A = torch.randn(O, I) * 0.3, torch.randn(O, I) * 0.3
    E0 = (torch.randn(B, O, I) * 0.8).clamp(-1.2, 1.2)
    ep, q0, q = torch.randn(B, O) * 0.3, torch.rand(B, I), torch.rand(B, I)
    dY, dE1, dp = torch.randn(B, R, O), torch.randn(B, O, I), torch.randn(B, O)
    leaves = [t.clone().requires_grad_() for t in (X, W, A, E0, ep, q0, q)]
    Xl, Wl, Al, E0l, epl, q0l, ql = leaves
    E1 = (E0l * KEEP + epl[:, :, None] * q0l[:, None, :]).clamp(-E_MAX, E_MAX)
    Y = Xl @ (Wl + Al * E1).transpose(1, 2)
    r = (E1 * ql[:, None, :]).sum(-1)
    ((Y * dY).sum() + (E1 * dE1).sum() - (r * dp).sum()).backward()
    Y_k, E1_k, r_k = ext.forward(X, W, A, E0, ep, q0, q, KEEP, E_MAX)
    dX, dE0, sums, dq, dq0, dep = ext.backward(dY, X, W, A, E0, ep, q0, q, dE1, dp, True, KEEP, E_MAX)
    pairs = [(Y_k, Y), (E1_k, E1), (r_k, r), (dX, Xl.grad), (dE0, E0l.grad), (sums[0], Wl.grad), (sums[1], Al.grad),
             (dq, ql.grad), (dq0, q0l.grad), (dep, epl.grad)]
    return max(float((k - e.detach()).abs().max() / e.detach().abs().max().clamp_min(1e-12)) for k, e in pairs)


def time_layer(ext, ops, n_out, n_in, rows, need_x, batch=32, sets=24, rounds=3) -> dict:
    """Median ms per call of today's kernels and of the one-pass pair, cycling through ``sets`` sets of data."""
    W, A = torch.randn(n_out, n_in) * 0.1, torch.randn(n_out, n_in) * 0.1
    data = [dict(X=(torch.rand(batch, rows, n_in) < 0.1).float(), E=(torch.randn(batch, n_out, n_in) * 0.5).clamp(-1, 1),
                 post=torch.rand(batch, n_out), pre=torch.rand(batch, n_in), dY=torch.randn(batch, rows, n_out),
                 dE=torch.randn(batch, n_out, n_in) * 0.1, ep=torch.rand(batch, n_out) * 0.01,
                 q0=torch.rand(batch, n_in), dp=torch.randn(batch, n_out) * 0.01) for _ in range(sets)]

    def today_forward(d):
        ops.plastic_linear_forward(d["X"], W, A, d["E"])
        ops.trace_step_forward(d["E"], d["post"], d["pre"], 1 - KEEP, E_MAX, True)

    def today_backward(d):
        ops.trace_step_backward(d["dE"], d["E"], d["post"], d["pre"], 1 - KEEP, E_MAX, True)
        ops.plastic_linear_backward(d["dY"], d["X"], W, A, d["E"], need_x)

    def one_pass_forward(d):
        ext.forward(d["X"], W, A, d["E"], d["ep"], d["q0"], d["pre"], KEEP, E_MAX)

    def one_pass_backward(d):
        ext.backward(d["dY"], d["X"], W, A, d["E"], d["ep"], d["q0"], d["pre"], d["dE"], d["dp"], need_x, KEEP, E_MAX)

    kernels = {"today forward": today_forward, "one-pass forward": one_pass_forward,
               "today backward": today_backward, "one-pass backward": one_pass_backward}
    times: dict[str, list[float]] = {name: [] for name in kernels}
    for _ in range(rounds):  # interleaved
        for name, fn in kernels.items():
            for d in data[:4]:
                fn(d)
            start = time.perf_counter()
            for d in data:
                fn(d)
            times[name].append((time.perf_counter() - start) / sets * 1e3)
    return {name: sorted(t)[len(t) // 2] for name, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)
    from sb3_spikeplastic import _fast
    from sb3_spikeplastic._fast.allocator import cache_freed_blocks, keep_freed_memory

    keep_freed_memory()
    cache_freed_blocks()
    ops = _fast.load_ops()
    if ops is None:
        raise SystemExit("the compiled kernels are not available (no compiler, or SB3_SPIKEPLASTIC_NO_COMPILE is set)")
    ext = build()
    error = check(ext)
    print(f"one-pass kernels against eager autograd: largest relative error {error:.1e}")
    if error > 1e-5:
        raise SystemExit("the one-pass kernels disagree with eager autograd")
    rows = []
    for name, n_out, n_in, product_rows, need_x in LAYERS:
        ms = time_layer(ext, ops, n_out, n_in, product_rows, need_x)
        rows.append(dict(layer=name, **{k.replace(" ", "_") + "_ms": round(v, 3) for k, v in ms.items()}))
        print(f"{name}: forward {ms['today forward']:.3f} -> {ms['one-pass forward']:.3f} ms, "
              f"backward {ms['today backward']:.3f} -> {ms['one-pass backward']:.3f} ms (batch 32, per interval)")
    saved = sum(r["today_forward_ms"] + r["today_backward_ms"] - r["one-pass_forward_ms"] - r["one-pass_backward_ms"]
                for r in rows)
    print(f"saved per BPTT step of batch 32 (both layers, forward + backward): {saved:.2f} ms")
    result = dict(command=" ".join(["python", *sys.argv]), threads=args.threads, max_relative_error=error,
                  layers=rows, saved_ms_per_step=round(saved, 3), machine=describe_machine(args.threads))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
