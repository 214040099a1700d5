// GMR's S-step as one hand-written CUDA kernel: every Adam step of an S-step in one launch,
// one thread block per seed or, where the seeds all fit on the GPU at once, a thread-block cluster
// of 2, 4 or 8 blocks per seed, called from JAX through the XLA FFI (gmr_jax/policies/gmr_cuda.py).
//
// In a cluster every block keeps a whole copy of the state (the program, θ, the buffers) and runs
// a share of each phase's items (32 consecutive items per warp, as with one block); an item's
// results go into every block's copy through distributed shared memory, and the cluster's
// barrier ends the phase. Each item computes what it computes with one block, in the same order,
// so the trained weights are the same bit for bit whatever the launch form.
//
// The kernel runs a per-step *program* that the Python side builds from the layout (gmr_cuda.py
// ``program``): a list of phases, each a list of tasks whose items the block's threads share,
// with a barrier after each phase. The program names the layers (their place in the compact θ
// and in shared memory) and the activation buffers (their place in shared memory), so the
// kernel holds no knowledge of the networks' depths or widths. Task kinds:
//
//   GATHER       the minibatch's rows: their indices, weights and encoder inputs; g_z ← 0
//   FWD          out = act(A·W + b) (act: leaky ReLU, or none)
//   INGRAD       out (=, or +=) mask(D1·W1ᵀ [+ D2·W2ᵀ]), mask: where(h ≥ 0, g, slope·g) of the
//                layer below (the leaky ReLU's derivative, read off its output: slope > 0)
//   WGRAD        the weight gradient hᵀD and bias gradient ΣD of a layer, each entry's Adam step
//                at once (θ in shared memory, Adam's moments in global memory)
//   LATENT       μ_z, log σ²_z, z = μ + σ·ε and the KL term per entry
//   HEAD1..4     the head (gmr.fused_head): Ψ_Σ's factor L, Δu, ΔK, the products with Σ and P,
//                the cotangents of the gain and Cholesky outputs and of x̂, and each row's terms
//   LATENT_GRAD  the cotangents of μ_z and log σ²_z from g_z and the KL term
//
// The arithmetic is that of gmr_kernel.py's Pallas kernel (the packed form's closed forms),
// in float32 on the CUDA cores (fused multiply-adds, no TF32): each product's sum runs in its
// own order, so the results agree with the packed form to round-off.
//
// Ablations, for profiles only (gmr_cuda.py ABLATIONS; $GMR_JAX_CUDA_ABLATE): each
// GMR_CUDA_ABLATE_<NAME> macro leaves one part of the step's work out, so that the step's time
// without it shows what the part costs. The trained weights are then wrong.
//   MOMENTS      Adam's moments stay zero in registers: no global memory reads or writes
//   WGRAD_SUMS   each weight gradient sums one minibatch row instead of all
//   FWD_SUMS     the forward products keep their bias only
//   INGRAD_SUMS  the input gradients' products are left out
//   HEAD         the head's tasks (HEAD1..4) are left out
//   BARRIERS     no barrier between phases (the phases race)
// In an ablated build Adam's gradient may be zero or garbage; a non-normal one is replaced by a
// normal stand-in, so that Adam's square root stays on its fast path as in training (zero, tiny
// and non-finite arguments take a slower one) and the profile times the training build's path.
#include <cooperative_groups.h>
#include <cuda_runtime.h>

#include <cmath>
#include <cstdint>
#include <string>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;
namespace cg = cooperative_groups;

// Thread-block clusters need compute capability 9.0: for older GPUs the cluster forms are built
// as traps (the host never launches them there: max_clusters finds none, and a forced form fails
// at launch), so that the one-block form still builds.
#if !defined(__CUDA_ARCH__) || __CUDA_ARCH__ >= 900
#define GMR_CUDA_CLUSTERS 1
#else
#define GMR_CUDA_CLUSTERS 0
#endif

namespace {

#if defined(GMR_CUDA_ABLATE_MOMENTS) || defined(GMR_CUDA_ABLATE_WGRAD_SUMS) || defined(GMR_CUDA_ABLATE_FWD_SUMS) || \
    defined(GMR_CUDA_ABLATE_INGRAD_SUMS) || defined(GMR_CUDA_ABLATE_HEAD) || defined(GMR_CUDA_ABLATE_BARRIERS)
#define GMR_CUDA_ABLATED
#endif

constexpr int NT_MAX = 1024;     // threads per block with one block per seed
constexpr int CLUSTER_NT = 512;  // threads per block of a cluster, unless set
constexpr int RG = 4;     // rows per item of FWD and INGRAD
constexpr int KG = 4;     // weight rows per item of WGRAD (a multiple of 4)
constexpr int NSTATS = 8; // total, value, action, action_mse, cov, gain, latent_kl, recon

enum TaskKind { GATHER = 0, FWD, INGRAD, WGRAD, LATENT, HEAD1, HEAD2, HEAD3, HEAD4, LATENT_GRAD };

// The fixed buffers (gmr_cuda.py FIXED_BUFFERS names them in this order).
enum FixedBuffer {
  B_ROWS = 0, B_WROW, B_XIN, B_MU, B_LV, B_Z, B_KLT, B_XHAT, B_GOUT, B_COUT, B_DG, B_DC, B_DXH, B_GZ,
  B_GMU, B_GLV, B_DK, B_DKS, B_PDKS, B_L, B_T, B_PL, B_TS, B_SRN, B_RN, B_DU, B_PDU, B_TR, B_LDT,
  B_ROWSTAT, B_RED, B_SIG, B_PRC, B_XE, B_TGT, B_LDP, N_FIXED
};

// The program's header (ints); gmr_cuda.py HEADER names them in this order.
enum Header {
  H_DX = 0, H_DU, H_X, H_U, H_LAT, H_BS, H_B, H_N_THETA, H_STATS_FROM, H_N_LAYERS, H_N_BUFS, H_N_TASKS,
  H_N_PHASES, H_LAYERS, H_BUFS, H_TASKS, H_PHASES, H_THETA_SMEM, H_L_GAIN, H_L_CHOL, H_L_XHAT, H_CYCLES, H_PROGRAM,
  H_SIZE
};
constexpr int LAYER_INTS = 5;  // compact offset, shared-memory offset, K, N, row stride S
constexpr int BUF_INTS = 2;    // shared-memory offset, leading dimension
constexpr int TASK_INTS = 9;   // kind, items, args[7]
constexpr int PHASE_INTS = 3;  // first task, tasks, items

// The float parameters (gmr_cuda.py FLOATS names them in this order).
enum Floats {
  F_SLOPE = 0, F_ALPHA, F_S, F_C, F_HALF_LOG_INIT_VAR, F_RHO, F_LR, F_B1, F_ONE_MINUS_B1, F_B2,
  F_ONE_MINUS_B2, F_EPS, F_WD, F_DU, N_FLOATS
};

struct Args {
  const int32_t* idx;     // [steps, bs]
  const float* eps;       // [steps, bs, lat]
  const float* c1;        // [steps]
  const float* c2;        // [steps]
  const float* xn;        // [B, X]
  const float* xe;        // [B, X]
  const float* sig;       // [B, X, X]
  const float* tgt;       // [B, U]
  const float* prc;       // [B, U, U]
  const float* Kp;        // [B, U, X]
  const float* wt;        // [B]
  const float* logdet;    // [B]
  const float* scale;     // [X]
  const float* theta0;    // [n]
  const int32_t* program; // [H_PROGRAM ints]
  const float* floats;    // [N_FLOATS]
  float* theta;           // [n]
  float* m;               // [n]
  float* v;               // [n]
  float* stats;           // [steps, NSTATS]
  float* cycles;          // [phases + 1]: clock cycles of each phase (and of the statistics), all steps
  int32_t* form;          // [1]: the launch form that ran, blocks per seed · 10000 + threads per block
  int steps;
  // per-seed strides (elements)
  long long s_idx, s_eps, s_steps, s_xn, s_sig, s_u, s_uu, s_ux, s_b, s_x, s_theta, s_program, s_floats, s_stats,
      s_cycles;
};

struct Ctx {
  const int* prog;      // the program in shared memory
  float* sm;            // shared memory (floats)
  const float* f;       // float parameters
  Args a;
  int step;
  float rc1, rc2;       // 1 / Adam's bias corrections of the step
  float l2;             // this thread's Σθ² of the step's updated entries (before the update)
  int rank;             // the block's rank in its seed's cluster (0 with one block per seed)
};

__device__ __forceinline__ float* buf(const Ctx& c, int id) { return c.sm + c.prog[c.prog[H_BUFS] + id * BUF_INTS]; }
__device__ __forceinline__ int ld(const Ctx& c, int id) { return c.prog[c.prog[H_BUFS] + id * BUF_INTS + 1]; }
__device__ __forceinline__ const int* layer(const Ctx& c, int l) { return c.prog + c.prog[H_LAYERS] + l * LAYER_INTS; }
__device__ __forceinline__ int row_of(const Ctx& c, int r) { return __float_as_int(buf(c, B_ROWS)[r]); }

__device__ __forceinline__ float leaky(float x, float slope) { return x >= 0.f ? x : slope * x; }

// A store into shared memory. With C blocks per seed (a thread-block cluster) every block holds
// the whole state (θ, the program's buffers) and runs a share of each phase's items; an item's
// result goes into every block's copy: the block's own first, then the others' through
// distributed shared memory, so that after the cluster's barrier every copy is the same.
template <typename T>
struct Same { using type = T; };

template <int C, typename T>
__device__ __forceinline__ void put(const Ctx& c, T* p, typename Same<T>::type v) {
  *p = v;
  if constexpr (C > 1) {
#if GMR_CUDA_CLUSTERS
    cg::cluster_group cl = cg::this_cluster();
#pragma unroll
    for (int d = 1; d < C; ++d) *cl.map_shared_rank(p, (c.rank + d) % C) = v;
#else
    __trap();
#endif
  }
}

// put of four floats at p (16-byte aligned).
template <int C>
__device__ __forceinline__ void put4(const Ctx& c, float* p, float4 v) {
  put<C>(c, reinterpret_cast<float4*>(p), v);
}

// The barrier between phases: the block's, or the cluster's (which also orders the other
// blocks' stores into this block's shared memory before the reads that follow).
template <int C>
__device__ __forceinline__ void barrier() {
  if constexpr (C > 1) {
#if GMR_CUDA_CLUSTERS
    cg::this_cluster().sync();
#else
    __trap();
#endif
  } else {
    __syncthreads();
  }
}

// The block's rank in its seed's cluster.
template <int C>
__device__ __forceinline__ int cluster_rank() {
#if GMR_CUDA_CLUSTERS
  if constexpr (C > 1) return (int)cg::this_cluster().block_rank();
#endif
  return 0;
}

// Stores x into slot i of the first block's array a (shared memory).
template <int C>
__device__ __forceinline__ void put_first(float* a, int i, float x) {
#if GMR_CUDA_CLUSTERS
  if constexpr (C > 1) {
    *cg::this_cluster().map_shared_rank(&a[i], 0) = x;
    return;
  }
#endif
  a[i] = x;
}

// ---------------------------------------------------------------- the networks' tasks

// Activation and cotangent buffers whose rows a product reads four at a time have rows of a
// multiple of four floats, 16-byte aligned (program() pads them), so a thread reads 4 entries of a
// row in one instruction.
__device__ __forceinline__ float4 ld4(const float* p) { return *reinterpret_cast<const float4*>(p); }

// out[r, n] = act(Σ_k A[r, k] W[k, n] + b[n]) for RG rows r of one column n.
template <int C>
__device__ void fwd_item(const Ctx& c, const int* t, int i) {
  const int* L = layer(c, t[0]);
  const int K = L[2], N = L[3], S = L[4];
  const float* W = c.sm + L[1];
  const float* A = buf(c, t[1]);
  const int lda = ld(c, t[1]);
  float* out = buf(c, t[2]);
  const int ldo = ld(c, t[2]);
  const int bs = c.prog[H_BS];
  const int n = i % N, r0 = (i / N) * RG;
  const float* Ar[RG];
#pragma unroll
  for (int j = 0; j < RG; ++j) Ar[j] = A + min(r0 + j, bs - 1) * lda;
  float acc[RG];
#pragma unroll
  for (int j = 0; j < RG; ++j) acc[j] = 0.f;
#ifdef GMR_CUDA_ABLATE_FWD_SUMS
  int k = K;
#else
  int k = 0;
#endif
#pragma unroll 2
  for (; k + 4 <= K; k += 4) {
    const float w0 = W[k * S + n], w1 = W[(k + 1) * S + n], w2 = W[(k + 2) * S + n], w3 = W[(k + 3) * S + n];
#pragma unroll
    for (int j = 0; j < RG; ++j) {
      const float4 a = ld4(Ar[j] + k);
      acc[j] = fmaf(a.w, w3, fmaf(a.z, w2, fmaf(a.y, w1, fmaf(a.x, w0, acc[j]))));
    }
  }
  for (; k < K; ++k) {
    const float w = W[k * S + n];
#pragma unroll
    for (int j = 0; j < RG; ++j) acc[j] = fmaf(Ar[j][k], w, acc[j]);
  }
  const float b = W[K * S + n];
#pragma unroll
  for (int j = 0; j < RG; ++j) {
    if (r0 + j < bs) {
      const float pre = acc[j] + b;
      put<C>(c, &out[(r0 + j) * ldo + n], t[3] ? leaky(pre, c.f[F_SLOPE]) : pre);
    }
  }
}

// Σ_n D[r, n] W[k, n] for RG rows r of one input k, added into acc.
__device__ __forceinline__ void transposed_product(const Ctx& c, int l, int d, int k, int r0, float (&acc)[RG]) {
  const int* L = layer(c, l);
  const int N = L[3], S = L[4];
  const float* W = c.sm + L[1] + k * S;
  const float* D = buf(c, d);
  const int ldd = ld(c, d);
  const int bs = c.prog[H_BS];
  const float* Dr[RG];
#pragma unroll
  for (int j = 0; j < RG; ++j) Dr[j] = D + min(r0 + j, bs - 1) * ldd;
  int n = 0;
#pragma unroll 2
  for (; n + 4 <= N; n += 4) {
    const float w0 = W[n], w1 = W[n + 1], w2 = W[n + 2], w3 = W[n + 3];
#pragma unroll
    for (int j = 0; j < RG; ++j) {
      const float4 g = ld4(Dr[j] + n);
      acc[j] = fmaf(g.w, w3, fmaf(g.z, w2, fmaf(g.y, w1, fmaf(g.x, w0, acc[j]))));
    }
  }
  for (; n < N; ++n) {
    const float w = W[n];
#pragma unroll
    for (int j = 0; j < RG; ++j) acc[j] = fmaf(Dr[j][n], w, acc[j]);
  }
}

// out[r, k] (=, or += with t[6]) mask(Σ_n D1[r, n] W1[k, n] (+ Σ_n D2[r, n] W2[k, n])).
// t: layer1, D1, layer2 (-1: none), D2, out, mask buffer (-1: none), accumulate.
template <int C>
__device__ void ingrad_item(const Ctx& c, const int* t, int i) {
  const int K = layer(c, t[0])[2];
  const int k = i % K, r0 = (i / K) * RG;
  const int bs = c.prog[H_BS];
  float acc[RG], acc2[RG];
#pragma unroll
  for (int j = 0; j < RG; ++j) acc[j] = acc2[j] = 0.f;
#ifndef GMR_CUDA_ABLATE_INGRAD_SUMS
  transposed_product(c, t[0], t[1], k, r0, acc);
  if (t[2] >= 0) transposed_product(c, t[2], t[3], k, r0, acc2);
#endif
  float* out = buf(c, t[4]);
  const int ldo = ld(c, t[4]);
  const float slope = c.f[F_SLOPE];
#pragma unroll
  for (int j = 0; j < RG; ++j) {
    const int r = r0 + j;
    if (r >= bs) continue;
    float g = t[2] >= 0 ? acc[j] + acc2[j] : acc[j];
    if (t[6]) g = out[r * ldo + k] + g;
    if (t[5] >= 0) g = buf(c, t[5])[r * ld(c, t[5]) + k] >= 0.f ? g : slope * g;
    put<C>(c, &out[r * ldo + k], g);
  }
}

// One step of optax.adam on θ (shared memory) given its moments m, v (read before, written
// after by the caller) on the gradient g + β·2θ: gmr_jax.adam.adam_update's operations, with the
// step's bias corrections as reciprocals (c.rc1 = 1/c1, c.rc2 = 1/c2) and one fast division, so
// each entry costs a few instructions instead of three IEEE divisions (each rounds within an ulp
// or two of the packed form's).
template <int C>
__device__ __forceinline__ void adam(Ctx& c, float* theta, float& m, float& v, float g) {
  const float* f = c.f;
  const float th = *theta;
  c.l2 = fmaf(th, th, c.l2);
  g = g + f[F_WD] * (2.f * th);
#ifdef GMR_CUDA_ABLATED
  if (!(fabsf(g) >= 1e-10f && fabsf(g) <= 1e10f)) g = 1e-3f;
#endif
  m = f[F_ONE_MINUS_B1] * g + f[F_B1] * m;
  v = f[F_ONE_MINUS_B2] * (g * g) + f[F_B2] * v;
  put<C>(c, theta, th + -f[F_LR] * __fdividef(m * c.rc1, __fsqrt_rn(v * c.rc2) + f[F_EPS]));
}

// The gradients of KG weight rows k (row K: the bias) of one column n, and their Adam steps.
// t: layer, h (the layer's input), D (the cotangent of its output). The entries' moments are
// read from global memory before the sums (a compiler barrier keeps the reads there), so that
// their latency overlaps the arithmetic.
template <int C>
__device__ void wgrad_item(Ctx& c, const int* t, int i) {
  const int* L = layer(c, t[0]);
  const int K = L[2], N = L[3], S = L[4];
  const int n = i % N, k0 = (i / N) * KG;
  const float* h = buf(c, t[1]);
  const int ldh = ld(c, t[1]);
  const float* D = buf(c, t[2]);
  const int ldd = ld(c, t[2]);
#ifdef GMR_CUDA_ABLATE_WGRAD_SUMS
  const int bs = 1;
#else
  const int bs = c.prog[H_BS];
#endif
  float m[KG], v[KG];
  const long long g0 = (long long)L[0] + (long long)k0 * N + n;
#pragma unroll
  for (int q = 0; q < KG; ++q) {
#ifdef GMR_CUDA_ABLATE_MOMENTS
    m[q] = v[q] = 0.f;
#else
    m[q] = k0 + q <= K ? c.a.m[g0 + (long long)q * N] : 0.f;
    v[q] = k0 + q <= K ? c.a.v[g0 + (long long)q * N] : 0.f;
#endif
  }
  asm volatile("" ::: "memory");
  float acc[KG];
#pragma unroll
  for (int q = 0; q < KG; ++q) acc[q] = 0.f;
  if (k0 + KG <= K) {  // KG weight rows: h[r, k0 .. k0 + KG - 1] in KG / 4 reads
#pragma unroll 4
    for (int r = 0; r < bs; ++r) {
      const float d = D[r * ldd + n];
#pragma unroll
      for (int q = 0; q < KG; q += 4) {
        const float4 x = ld4(h + r * ldh + k0 + q);
        acc[q] = fmaf(x.x, d, acc[q]);
        acc[q + 1] = fmaf(x.y, d, acc[q + 1]);
        acc[q + 2] = fmaf(x.z, d, acc[q + 2]);
        acc[q + 3] = fmaf(x.w, d, acc[q + 3]);
      }
    }
  } else {
    for (int r = 0; r < bs; ++r) {
      const float d = D[r * ldd + n];
#pragma unroll
      for (int q = 0; q < KG; ++q) {
        const int k = k0 + q;
        acc[q] = k < K ? fmaf(h[r * ldh + k], d, acc[q]) : (k == K ? acc[q] + d : acc[q]);
      }
    }
  }
#pragma unroll
  for (int q = 0; q < KG; ++q) {
    const int k = k0 + q;
    if (k <= K) {
      adam<C>(c, c.sm + L[1] + k * S + n, m[q], v[q], acc[q]);
#ifndef GMR_CUDA_ABLATE_MOMENTS
      c.a.m[g0 + (long long)q * N] = m[q];
      c.a.v[g0 + (long long)q * N] = v[q];
#endif
    }
  }
}

// ---------------------------------------------------------------- the latent state

// t: μ layer, log σ² layer, input buffer.  Items (r, j): μ, log σ², z, the KL term.
template <int C>
__device__ void latent_item(const Ctx& c, const int* t, int i) {
  const int lat = c.prog[H_LAT];
  const int r = i / lat, j = i % lat;
  const int* Lm = layer(c, t[0]);
  const int* Lv = layer(c, t[1]);
  const int K = Lm[2];
  const float* h = buf(c, t[2]) + r * ld(c, t[2]);
  const float* Wm = c.sm + Lm[1];
  const float* Wv = c.sm + Lv[1];
  float mu = 0.f, lv = 0.f;
  for (int k = 0; k < K; ++k) {
    mu = fmaf(h[k], Wm[k * Lm[4] + j], mu);
    lv = fmaf(h[k], Wv[k * Lv[4] + j], lv);
  }
  mu = mu + Wm[K * Lm[4] + j];
  lv = lv + Wv[K * Lv[4] + j];
  const float sd = expf(0.5f * lv), var = expf(lv);
  const float e = c.a.eps[((long long)c.step * c.prog[H_BS] + r) * lat + j];
  put<C>(c, &buf(c, B_MU)[r * ld(c, B_MU) + j], mu);
  put<C>(c, &buf(c, B_LV)[r * ld(c, B_LV) + j], lv);
  put<C>(c, &buf(c, B_Z)[r * ld(c, B_Z) + j], mu + sd * e);
  put<C>(c, &buf(c, B_KLT)[r * ld(c, B_KLT) + j], mu * mu + var - lv - 1.f);
}

template <int C>
__device__ void latent_grad_item(const Ctx& c, int i) {
  const int lat = c.prog[H_LAT];
  const int r = i / lat, j = i % lat;
  const float w = buf(c, B_WROW)[r];
  const float ct = c.f[F_ALPHA] * 0.5f * c.f[F_RHO] * w;
  const float mu = buf(c, B_MU)[r * ld(c, B_MU) + j], lv = buf(c, B_LV)[r * ld(c, B_LV) + j];
  const float gz = buf(c, B_GZ)[r * ld(c, B_GZ) + j];
  const float e = c.a.eps[((long long)c.step * c.prog[H_BS] + r) * lat + j];
  put<C>(c, &buf(c, B_GMU)[r * ld(c, B_GMU) + j], gz + ct * (2.f * mu));
  put<C>(c, &buf(c, B_GLV)[r * ld(c, B_GLV) + j], gz * e * (0.5f * expf(0.5f * lv)) + ct * (expf(lv) - 1.f));
}

__device__ __forceinline__ int pad4(int n) { return (n + 3) & ~3; }

// The minibatch's rows: their indices, weights and encoder inputs, g_z ← 0, and the head's
// per-row data (Σ_t, P, the head's input x̃, the target, log|P|) copied into shared memory four
// floats at a time, so that the head's phases read no global memory.
template <int C>
__device__ void gather_item(const Ctx& c, int i) {
  const int bs = c.prog[H_BS], dX = c.prog[H_DX], dU = c.prog[H_DU], X = c.prog[H_X], U = c.prog[H_U];
  const int* idx = c.a.idx + (long long)c.step * bs;
  if (i < bs * dX) {
    const int r = i / dX, j = i % dX;
    const int row = idx[r];
    put<C>(c, &buf(c, B_XIN)[r * ld(c, B_XIN) + j], c.a.xn[(long long)row * X + j]);
    if (j == 0) {
      put<C>(c, &buf(c, B_ROWS)[r], __int_as_float(row));
      put<C>(c, &buf(c, B_WROW)[r], c.a.wt[row]);
      put<C>(c, &buf(c, B_LDP)[r], c.a.logdet[row]);
    }
    return;
  }
  i -= bs * dX;
  const int ngz = bs * ld(c, B_GZ);
  if (i < ngz) {
    put<C>(c, &buf(c, B_GZ)[i], 0.f);
    return;
  }
  i -= ngz;
  const int qx = pad4(dX) / 4, qu = pad4(dU) / 4, qe = pad4(dX + 1) / 4;
  if (i < bs * dX * qx) {  // Σ_t: row j of dX entries (padded to a multiple of four)
    const int r = i / (dX * qx), j = (i / qx) % dX, q = i % qx;
    const float4 v = ld4(c.a.sig + ((long long)idx[r] * X + j) * X + 4 * q);
    put4<C>(c, buf(c, B_SIG) + r * ld(c, B_SIG) + j * pad4(dX) + 4 * q, v);
    return;
  }
  i -= bs * dX * qx;
  if (i < bs * dU * qu) {  // P: row a of dU entries
    const int r = i / (dU * qu), a = (i / qu) % dU, q = i % qu;
    const float4 v = ld4(c.a.prc + ((long long)idx[r] * U + a) * U + 4 * q);
    put4<C>(c, buf(c, B_PRC) + r * ld(c, B_PRC) + a * pad4(dU) + 4 * q, v);
    return;
  }
  i -= bs * dU * qu;
  if (i < bs * qe) {  // x̃ with its constant 1
    const int r = i / qe, q = i % qe;
    put4<C>(c, buf(c, B_XE) + r * ld(c, B_XE) + 4 * q, ld4(c.a.xe + (long long)idx[r] * X + 4 * q));
    return;
  }
  i -= bs * qe;
  const int r = i / qu, q = i % qu;  // the target
  put4<C>(c, buf(c, B_TGT) + r * ld(c, B_TGT) + 4 * q, ld4(c.a.tgt + (long long)idx[r] * U + 4 * q));
}

// ---------------------------------------------------------------- the head (gmr.fused_head)

// Items (r, i), i < dU: row i of L and of tanh(r/c) (V's strictly lower entries are c·tanh(r/c),
// its diagonal 1), tanh of the diagonal, Δu_i, log σ_i − log‖V_i‖;
// then items (r, i, j), j < dX: ΔK = G·diag(scale) − K.
template <int C>
__device__ void head1_item(const Ctx& c, int i) {
  const int dU = c.prog[H_DU], dX = c.prog[H_DX], X = c.prog[H_X], U = c.prog[H_U], bs = c.prog[H_BS];
  const float* f = c.f;
  if (i < bs * dU) {
    const int r = i / dU, a = i % dU;
    const float* Co = buf(c, B_COUT) + r * ld(c, B_COUT);
    const float* G = buf(c, B_GOUT) + r * ld(c, B_GOUT);
    const float tt = tanhf(Co[a * U + a] / f[F_S]);
    const float log_sigma = f[F_HALF_LOG_INIT_VAR] + f[F_S] * tt;
    float* T = buf(c, B_T) + r * dU * dU + a * dU;
    float ss = 0.f;
#pragma unroll 4
    for (int b = 0; b < dU; ++b) {
      const float Tb = tanhf(Co[a * U + b] / f[F_C]);
      const float Vb = (b < a ? f[F_C] * Tb : 0.f) + (b == a ? 1.f : 0.f);
      put<C>(c, &T[b], Tb);
      ss = fmaf(Vb, Vb, ss);
    }
    const float rn = sqrtf(ss), sigma = expf(log_sigma), srn = sigma / rn;
    float* Lr = buf(c, B_L) + r * dU * dU + a * dU;
    for (int b = 0; b < dU; ++b) put<C>(c, &Lr[b], srn * ((b < a ? f[F_C] * T[b] : 0.f) + (b == a ? 1.f : 0.f)));
    put<C>(c, &buf(c, B_TS)[r * dU + a], tt);
    put<C>(c, &buf(c, B_SRN)[r * dU + a], srn);
    put<C>(c, &buf(c, B_RN)[r * dU + a], rn);
    put<C>(c, &buf(c, B_LDT)[r * dU + a], log_sigma - logf(rn));
    const float* xe = buf(c, B_XE) + r * ld(c, B_XE);
    float du = 0.f;
    #pragma unroll 4
    for (int j = 0; j <= dX; ++j) du = fmaf(G[a * X + j], xe[j], du);
    put<C>(c, &buf(c, B_DU)[r * dU + a], du - buf(c, B_TGT)[r * ld(c, B_TGT) + a]);
  } else {
    i -= bs * dU;
    const int r = i / (dU * dX), a = (i / dX) % dU, j = i % dX, row = row_of(c, r);
    const float* G = buf(c, B_GOUT) + r * ld(c, B_GOUT);
    put<C>(c, &buf(c, B_DK)[r * dU * dX + a * dX + j], G[a * X + j] * c.a.scale[j] - c.a.Kp[((long long)row * U + a) * X + j]);
  }
}

// Σ_k P[a, k] Y[k, j]: row a of row r's P (shared memory) times column j of Y [dU, cols].
__device__ __forceinline__ float p_row_times(const Ctx& c, int r, int a, const float* Y, int cols, int j) {
  const int dU = c.prog[H_DU];
  const float* P = buf(c, B_PRC) + r * ld(c, B_PRC) + a * pad4(dU);
  float s = 0.f;
#pragma unroll 4
  for (int k = 0; k < dU; ++k) s = fmaf(P[k], Y[k * cols + j], s);
  return s;
}

// ΔK Σ (r, i, j < dX); P Δu (r, i); P L (r, i, j < dU).
template <int C>
__device__ void head2_item(const Ctx& c, int i) {
  const int dU = c.prog[H_DU], dX = c.prog[H_DX], bs = c.prog[H_BS];
  if (i < bs * dU * dX) {
    const int r = i / (dU * dX), a = (i / dX) % dU, j = i % dX;
    const float* dK = buf(c, B_DK) + r * dU * dX + a * dX;
    const float* sg = buf(c, B_SIG) + r * ld(c, B_SIG) + j * pad4(dX);
    float s = 0.f;
    #pragma unroll 4
    for (int k = 0; k < dX; ++k) s = fmaf(dK[k], sg[k], s);
    put<C>(c, &buf(c, B_DKS)[r * dU * dX + a * dX + j], s);
    return;
  }
  i -= bs * dU * dX;
  if (i < bs * dU) {
    const int r = i / dU, a = i % dU;
    const float* P = buf(c, B_PRC) + r * ld(c, B_PRC) + a * pad4(dU);
    const float* du = buf(c, B_DU) + r * dU;
    float s = 0.f;
    #pragma unroll 4
    for (int b = 0; b < dU; ++b) s = fmaf(P[b], du[b], s);
    put<C>(c, &buf(c, B_PDU)[r * dU + a], s);
    return;
  }
  i -= bs * dU;
  const int r = i / (dU * dU), a = (i / dU) % dU, b = i % dU;
  put<C>(c, &buf(c, B_PL)[r * dU * dU + a * dU + b], p_row_times(c, r, a, buf(c, B_L) + r * dU * dU, dU, b));
}

// P ΔK Σ (r, i, j < dX); the rows of tr(Lᵀ P L) (r, i).
template <int C>
__device__ void head3_item(const Ctx& c, int i) {
  const int dU = c.prog[H_DU], dX = c.prog[H_DX], bs = c.prog[H_BS];
  if (i < bs * dU * dX) {
    const int r = i / (dU * dX), a = (i / dX) % dU, j = i % dX;
    put<C>(c, &buf(c, B_PDKS)[r * dU * dX + a * dX + j], p_row_times(c, r, a, buf(c, B_DKS) + r * dU * dX, dX, j));
    return;
  }
  i -= bs * dU * dX;
  const int r = i / dU, a = i % dU;
  const float* L = buf(c, B_L) + r * dU * dU + a * dU;
  const float* PL = buf(c, B_PL) + r * dU * dU + a * dU;
  float s = 0.f;
  for (int b = 0; b < dU; ++b) s = fmaf(L[b], PL[b], s);
  put<C>(c, &buf(c, B_TR)[r * dU + a], s);
}

// The cotangents of the gain output (r, n < NG), the Cholesky output (r, n < NC) and x̂
// (r, j < dX); each row's loss terms (r).
template <int C>
__device__ void head4_item(const Ctx& c, int i) {
  const int dU = c.prog[H_DU], dX = c.prog[H_DX], X = c.prog[H_X], U = c.prog[H_U], bs = c.prog[H_BS];
  const int NG = layer(c, c.prog[H_L_GAIN])[3], NC = layer(c, c.prog[H_L_CHOL])[3];
  const float* f = c.f;
  const float rho = f[F_RHO];
  if (i < bs * NG) {
    const int r = i / NG, n = i % NG, a = n / X, j = n % X;
    const float xe = j <= dX ? buf(c, B_XE)[r * ld(c, B_XE) + j] : 0.f;  // x̃ is zero beyond its 1
    float g = (rho * buf(c, B_PDU)[r * dU + a]) * xe;
    if (j < dX) g = g + (rho * buf(c, B_PDKS)[r * dU * dX + a * dX + j]) * c.a.scale[j];
    put<C>(c, &buf(c, B_DG)[r * ld(c, B_DG) + n], g);
    return;
  }
  i -= bs * NG;
  if (i < bs * NC) {
    const int r = i / NC, n = i % NC, a = n / U, b = n % U;
    float g = 0.f;
    if (a < dU && b <= a) {
      const float q = rho * buf(c, B_TR)[r * dU + a] + (-rho) * buf(c, B_WROW)[r];
      if (b < a) {
        const int e = r * dU * dU + a * dU + b;
        const float rn = buf(c, B_RN)[r * dU + a];
        const float gV = buf(c, B_SRN)[r * dU + a] * (rho * buf(c, B_PL)[e]) - (q / (rn * rn)) * (f[F_C] * buf(c, B_T)[e]);
        const float T = buf(c, B_T)[e];
        g = gV * (1.f - T * T);
      } else {
        const float tt = buf(c, B_TS)[r * dU + a];
        g = q * (1.f - tt * tt);
      }
    }
    put<C>(c, &buf(c, B_DC)[r * ld(c, B_DC) + n], g);
    return;
  }
  i -= bs * NC;
  if (i < bs * dX) {
    const int r = i / dX, j = i % dX;
    const float w = buf(c, B_WROW)[r];
    const float diff = buf(c, B_XIN)[r * ld(c, B_XIN) + j] - buf(c, B_XHAT)[r * ld(c, B_XHAT) + j];
    put<C>(c, &buf(c, B_DXH)[r * ld(c, B_DXH) + j], (-2.f * rho * w) * diff);
    return;
  }
  // the row's loss terms, in STATS order after total and value:
  // action, action_mse, cov, gain, latent_kl, recon; only the steps with statistics read them
  if (c.step < c.prog[H_STATS_FROM]) return;
  const int r = i - bs * dX, lat = c.prog[H_LAT];
  const float w = buf(c, B_WROW)[r];
  const float* du = buf(c, B_DU) + r * dU;
  const float* pdu = buf(c, B_PDU) + r * dU;
  float action = 0.f, mse = 0.f, tr = 0.f, ldt = 0.f;
  for (int a = 0; a < dU; ++a) {
    action = fmaf(du[a], pdu[a], action);
    mse = fmaf(du[a], du[a], mse);
    tr = tr + buf(c, B_TR)[r * dU + a];
    ldt = ldt + buf(c, B_LDT)[r * dU + a];
  }
  float gain = 0.f;
  const float* dK = buf(c, B_DK) + r * dU * dX;
  const float* pdks = buf(c, B_PDKS) + r * dU * dX;
  for (int e = 0; e < dU * dX; ++e) gain = fmaf(dK[e], pdks[e], gain);
  float recon = 0.f;
  for (int j = 0; j < dX; ++j) {
    const float diff = buf(c, B_XIN)[r * ld(c, B_XIN) + j] - buf(c, B_XHAT)[r * ld(c, B_XHAT) + j];
    recon = fmaf(diff, diff, recon);
  }
  float kl = 0.f;
  for (int j = 0; j < lat; ++j) kl = kl + buf(c, B_KLT)[r * ld(c, B_KLT) + j];
  float* out = buf(c, B_ROWSTAT) + r * (NSTATS - 2);
  put<C>(c, &out[0], action);
  put<C>(c, &out[1], mse / f[F_DU]);
  put<C>(c, &out[2], tr - w * (2.f * ldt + f[F_DU] + buf(c, B_LDP)[r]));
  put<C>(c, &out[3], gain);
  put<C>(c, &out[4], w * 0.5f * kl);
  put<C>(c, &out[5], w * recon);
}

// ---------------------------------------------------------------- the kernel

template <int C>
__device__ __forceinline__ void run_item(Ctx& c, const int* t, int i) {
  switch (t[0]) {
    case GATHER: gather_item<C>(c, i); break;
    case FWD: fwd_item<C>(c, t + 2, i); break;
    case INGRAD: ingrad_item<C>(c, t + 2, i); break;
    case WGRAD: wgrad_item<C>(c, t + 2, i); break;
    case LATENT: latent_item<C>(c, t + 2, i); break;
#ifndef GMR_CUDA_ABLATE_HEAD
    case HEAD1: head1_item<C>(c, i); break;
    case HEAD2: head2_item<C>(c, i); break;
    case HEAD3: head3_item<C>(c, i); break;
    case HEAD4: head4_item<C>(c, i); break;
#endif
    case LATENT_GRAD: latent_grad_item<C>(c, i); break;
  }
}

template <int NT>
__device__ float block_sum(float x, float* red) {
  for (int o = 16; o > 0; o >>= 1) x += __shfl_xor_sync(0xffffffffu, x, o);
  const int warp = threadIdx.x / 32, lane = threadIdx.x % 32;
  if (lane == 0) red[warp] = x;
  __syncthreads();
  float s = 0.f;
  if (warp == 0) {
    s = lane < NT / 32 ? red[lane] : 0.f;
    for (int o = 16; o > 0; o >>= 1) s += __shfl_xor_sync(0xffffffffu, s, o);
  }
  return s;  // the sum in thread 0 (warp 0)
}

// One seed's S-step on C blocks (C = 1: one block; C > 1: a thread-block cluster, whose blocks
// share each phase's items and keep identical copies of the state).
// Every item computes what it computes with one block, in the same order, so the weights do not
// depend on C.
template <int C, int NT>
__global__ void __launch_bounds__(NT, 1) gmr_sstep_kernel(Args a) {
  extern __shared__ float sm[];
  const int seed = blockIdx.x / C;
  const int rank = cluster_rank<C>();
  a.idx += seed * a.s_idx; a.eps += seed * a.s_eps; a.c1 += seed * a.s_steps; a.c2 += seed * a.s_steps;
  a.xn += seed * a.s_xn; a.xe += seed * a.s_xn; a.sig += seed * a.s_sig; a.tgt += seed * a.s_u;
  a.prc += seed * a.s_uu; a.Kp += seed * a.s_ux; a.wt += seed * a.s_b; a.logdet += seed * a.s_b;
  a.scale += seed * a.s_x; a.theta0 += seed * a.s_theta; a.program += seed * a.s_program;
  a.floats += seed * a.s_floats; a.theta += seed * a.s_theta; a.m += seed * a.s_theta;
  a.v += seed * a.s_theta; a.stats += seed * a.s_stats; a.cycles += seed * a.s_cycles; a.form += seed;

  int* prog = reinterpret_cast<int*>(sm);
  const int np = a.program[H_PROGRAM];
  for (int i = threadIdx.x; i < np; i += NT) prog[i] = a.program[i];
  __syncthreads();
  // θ into shared memory (rows of stride S), Adam's moments to zero (a cluster's blocks a share
  // each, ordered before any block's Adam by the barrier below)
  const int nl = prog[H_N_LAYERS];
  for (int l = 0; l < nl; ++l) {
    const int* L = prog + prog[H_LAYERS] + l * LAYER_INTS;
    const int K1 = L[2] + 1, N = L[3], S = L[4];
    for (int e = threadIdx.x; e < K1 * N; e += NT) sm[L[1] + (e / N) * S + e % N] = a.theta0[L[0] + e];
  }
  for (int e = rank * NT + threadIdx.x; e < prog[H_N_THETA]; e += C * NT) { a.m[e] = 0.f; a.v[e] = 0.f; }

  // the float parameters in shared memory: read there, Adam's constants are not reloaded from
  // global memory after each of its moments' stores (which the compiler cannot tell apart)
  __shared__ float fsm[N_FLOATS];
  // the blocks' Σθ² of a step, gathered in the first block of the cluster
  __shared__ float l2s[C];
  if (threadIdx.x < N_FLOATS) fsm[threadIdx.x] = a.floats[threadIdx.x];
  // a cluster's blocks have all started (their shared memory can be written) after this barrier
  barrier<C>();
  Ctx c{prog, sm, fsm, a, 0, 0.f, 0.f, 0.f, rank};
  float* red = buf(c, B_RED);
  const int* phases = prog + prog[H_PHASES];
  const int* tasks = prog + prog[H_TASKS];
  // each phase's clock cycles (thread 0, after the phase's barrier), in shared memory: a profile
  // that costs a clock read and an add per phase
  double* cycles = reinterpret_cast<double*>(sm + prog[prog[H_BUFS] + prog[H_CYCLES] * BUF_INTS]);
  const int nph = prog[H_N_PHASES];
  if (threadIdx.x == 0)
    for (int p = 0; p <= nph; ++p) cycles[p] = 0.0;
  long long clock0 = clock64();
  for (int step = 0; step < a.steps; ++step) {
    c.step = step;
    c.rc1 = 1.f / a.c1[step];
    c.rc2 = 1.f / a.c2[step];
    c.l2 = 0.f;
    for (int p = 0; p < prog[H_N_PHASES]; ++p) {
      const int* ph = phases + p * PHASE_INTS;
      // item i on block (i / 32) mod C: each warp runs 32 consecutive items, as with one block
      // (coalesced global reads, conflict-free shared memory)
      for (int j = threadIdx.x;; j += NT) {
        const int i = ((j >> 5) * C + rank) * 32 + (j & 31);
        if (i >= ph[2]) break;
        int t = ph[0], base = 0;
        while (i >= base + tasks[t * TASK_INTS + 1]) { base += tasks[t * TASK_INTS + 1]; ++t; }
        run_item<C>(c, tasks + t * TASK_INTS, i - base);
      }
#ifndef GMR_CUDA_ABLATE_BARRIERS
      barrier<C>();
#endif
      if (threadIdx.x == 0) {
        const long long now = clock64();
        cycles[p] += (double)(now - clock0);
        clock0 = now;
      }
    }
    float* st = a.stats + (long long)step * NSTATS;
    if (step >= prog[H_STATS_FROM]) {
      float l2 = block_sum<NT>(c.l2, red);
      if constexpr (C > 1) {  // the blocks' sums, added in rank order in the first block
        if (threadIdx.x == 0) put_first<C>(l2s, rank, l2);
        barrier<C>();
        if (threadIdx.x == 0 && rank == 0) {
          l2 = 0.f;
          for (int q = 0; q < C; ++q) l2 = l2 + l2s[q];
        }
      }
      if (threadIdx.x == 0 && rank == 0) {
        const float* f = a.floats;
        const int bs = prog[H_BS];
        const float* rs = buf(c, B_ROWSTAT);
        float aux[NSTATS - 2];
        for (int k = 0; k < NSTATS - 2; ++k) {
          float s = 0.f;
          for (int r = 0; r < bs; ++r) s = s + f[F_RHO] * rs[r * (NSTATS - 2) + k];
          aux[k] = s;
        }
        aux[0] = 0.5f * aux[0];  // action
        aux[2] = 0.5f * aux[2];  // cov
        aux[3] = 0.5f * aux[3];  // gain
        const float value = aux[5] + f[F_ALPHA] * aux[4] + aux[0] + aux[3] + aux[2];
        st[0] = value + f[F_WD] * l2;
        st[1] = value;
        for (int k = 0; k < NSTATS - 2; ++k) st[2 + k] = aux[k];
      }
      __syncthreads();
    } else if (threadIdx.x < NSTATS && rank == 0) {
      st[threadIdx.x] = 0.f;
    }
    if (threadIdx.x == 0) {
      const long long now = clock64();
      cycles[nph] += (double)(now - clock0);
      clock0 = now;
    }
  }
  if (rank == 0) {
    if (threadIdx.x == 0)
      for (int p = 0; p <= nph; ++p) a.cycles[p] = (float)cycles[p];
    for (int l = 0; l < nl; ++l) {
      const int* L = prog + prog[H_LAYERS] + l * LAYER_INTS;
      const int K1 = L[2] + 1, N = L[3], S = L[4];
      for (int e = threadIdx.x; e < K1 * N; e += NT) a.theta[L[0] + e] = sm[L[1] + (e / N) * S + e % N];
    }
  }
  if (rank == 0 && threadIdx.x == 0) *a.form = C * 10000 + NT;
  // no block leaves while another may still write into its shared memory
  if constexpr (C > 1) barrier<C>();
}

// The launch of C blocks of NT threads per seed (a cluster of C blocks for C > 1) into cfg, its
// cluster attribute into attr; sets the kernel's shared memory.
template <int C, int NT>
cudaError_t configure(cudaLaunchConfig_t& cfg, cudaLaunchAttribute (&attr)[1], long long seeds, int64_t smem_bytes,
                      cudaStream_t stream) {
  cfg = cudaLaunchConfig_t{};
  cfg.gridDim = dim3((unsigned)(seeds * C));
  cfg.blockDim = dim3(NT);
  cfg.dynamicSmemBytes = (size_t)smem_bytes;
  cfg.stream = stream;
  attr[0].id = cudaLaunchAttributeClusterDimension;
  attr[0].val.clusterDim.x = C;
  attr[0].val.clusterDim.y = 1;
  attr[0].val.clusterDim.z = 1;
  cfg.attrs = attr;
  cfg.numAttrs = C > 1 ? 1 : 0;
  return cudaFuncSetAttribute(gmr_sstep_kernel<C, NT>, cudaFuncAttributeMaxDynamicSharedMemorySize, (int)smem_bytes);
}

template <int C, int NT>
cudaError_t launch(const Args& a, long long seeds, int64_t smem_bytes, cudaStream_t stream) {
  cudaLaunchConfig_t cfg;
  cudaLaunchAttribute attr[1];
  cudaError_t err = configure<C, NT>(cfg, attr, seeds, smem_bytes, stream);
  if (err == cudaSuccess) err = cudaLaunchKernelEx(&cfg, gmr_sstep_kernel<C, NT>, a);
  // a failed call's error is also the runtime's last error: read (and clear) it here, so that
  // it is not reported again by a later launch
  const cudaError_t last = cudaGetLastError();
  return err == cudaSuccess ? last : err;
}

// How many clusters of C blocks (CLUSTER_NT threads each) the GPU runs at once (0 where it
// runs none, e.g. a GPU without clusters).
template <int C>
int max_clusters(int64_t smem_bytes) {
  cudaLaunchConfig_t cfg;
  cudaLaunchAttribute attr[1];
  int n = 0;
  cudaError_t err = configure<C, CLUSTER_NT>(cfg, attr, 1, smem_bytes, nullptr);
  if (err == cudaSuccess) err = cudaOccupancyMaxActiveClusters(&n, gmr_sstep_kernel<C, CLUSTER_NT>, &cfg);
  if (err != cudaSuccess) {
    cudaGetLastError();  // clear the error: one block per seed instead
    return 0;
  }
  return n;
}

// The launch form, blocks per seed · 10000 + threads per block: ``form`` where given (not 0), else
// the largest cluster whose seeds all run at once, or one block of NT_MAX threads per seed.
int64_t launch_form(long long seeds, int64_t smem_bytes, int64_t form) {
  if (form != 0) return form;
  const int cluster = seeds <= max_clusters<8>(smem_bytes) ? 8
                      : seeds <= max_clusters<4>(smem_bytes) ? 4
                      : seeds <= max_clusters<2>(smem_bytes) ? 2 : 1;
  return cluster * 10000 + (cluster == 1 ? NT_MAX : CLUSTER_NT);
}

long long per_seed(const ffi::AnyBuffer& b, long long seeds) { return (long long)b.element_count() / seeds; }

ffi::Error gmr_sstep(cudaStream_t stream, ffi::AnyBuffer idx, ffi::AnyBuffer eps, ffi::AnyBuffer c1,
                     ffi::AnyBuffer c2, ffi::AnyBuffer xn, ffi::AnyBuffer xe, ffi::AnyBuffer sig, ffi::AnyBuffer tgt,
                     ffi::AnyBuffer prc, ffi::AnyBuffer Kp, ffi::AnyBuffer wt, ffi::AnyBuffer logdet,
                     ffi::AnyBuffer scale, ffi::AnyBuffer theta0, ffi::AnyBuffer program, ffi::AnyBuffer floats,
                     ffi::Result<ffi::AnyBuffer> theta, ffi::Result<ffi::AnyBuffer> m, ffi::Result<ffi::AnyBuffer> v,
                     ffi::Result<ffi::AnyBuffer> stats, ffi::Result<ffi::AnyBuffer> cycles,
                     ffi::Result<ffi::AnyBuffer> form_used, int64_t steps, int64_t smem_bytes, int64_t form) {
  if (idx.element_type() != ffi::DataType::S32 || program.element_type() != ffi::DataType::S32 ||
      eps.element_type() != ffi::DataType::F32 || theta0.element_type() != ffi::DataType::F32)
    return ffi::Error::InvalidArgument("gmr_sstep_cuda: idx and program must be int32, the rest float32");
  const auto dims = idx.dimensions();
  if (dims.size() < 2) return ffi::Error::InvalidArgument("gmr_sstep_cuda: idx must be [..., steps, batch]");
  const long long per = (long long)dims[dims.size() - 1] * (long long)dims[dims.size() - 2];
  const long long seeds = per > 0 ? (long long)idx.element_count() / per : 0;
  if (seeds < 1 || steps < 1) return ffi::Error::InvalidArgument("gmr_sstep_cuda: no seeds or no steps");
  if ((long long)dims[dims.size() - 2] != steps)
    return ffi::Error::InvalidArgument("gmr_sstep_cuda: idx's steps differ from the steps attribute");
  Args a{};
  a.idx = idx.typed_data<int32_t>(); a.eps = eps.typed_data<float>(); a.c1 = c1.typed_data<float>();
  a.c2 = c2.typed_data<float>(); a.xn = xn.typed_data<float>(); a.xe = xe.typed_data<float>();
  a.sig = sig.typed_data<float>(); a.tgt = tgt.typed_data<float>(); a.prc = prc.typed_data<float>();
  a.Kp = Kp.typed_data<float>(); a.wt = wt.typed_data<float>(); a.logdet = logdet.typed_data<float>();
  a.scale = scale.typed_data<float>(); a.theta0 = theta0.typed_data<float>();
  a.program = program.typed_data<int32_t>(); a.floats = floats.typed_data<float>();
  a.theta = theta->typed_data<float>(); a.m = m->typed_data<float>(); a.v = v->typed_data<float>();
  a.stats = stats->typed_data<float>();
  a.cycles = cycles->typed_data<float>();
  a.form = form_used->typed_data<int32_t>();
  a.steps = (int)steps;
  a.s_idx = per_seed(idx, seeds); a.s_eps = per_seed(eps, seeds); a.s_steps = per_seed(c1, seeds);
  a.s_xn = per_seed(xn, seeds); a.s_sig = per_seed(sig, seeds); a.s_u = per_seed(tgt, seeds);
  a.s_uu = per_seed(prc, seeds); a.s_ux = per_seed(Kp, seeds); a.s_b = per_seed(wt, seeds);
  a.s_x = per_seed(scale, seeds); a.s_theta = per_seed(theta0, seeds); a.s_program = per_seed(program, seeds);
  a.s_floats = per_seed(floats, seeds); a.s_stats = per_seed(*stats, seeds);
  a.s_cycles = per_seed(*cycles, seeds);
  cudaError_t err = cudaErrorInvalidConfiguration;
  switch (launch_form(seeds, smem_bytes, form)) {
    case 11024: err = launch<1, 1024>(a, seeds, smem_bytes, stream); break;
    case 20512: err = launch<2, 512>(a, seeds, smem_bytes, stream); break;
    case 40512: err = launch<4, 512>(a, seeds, smem_bytes, stream); break;
    case 80256: err = launch<8, 256>(a, seeds, smem_bytes, stream); break;
    case 80512: err = launch<8, 512>(a, seeds, smem_bytes, stream); break;
    default:
      return ffi::Error::InvalidArgument("gmr_sstep_cuda: the form attribute names no built form (10000 · blocks "
                                         "+ threads: 11024, 20512, 40512, 80256, 80512; 0 for the library's choice)");
  }
  if (err != cudaSuccess)
    return ffi::Error::Internal(std::string("gmr_sstep_cuda: ") + cudaGetErrorString(err));
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(GmrSstepCuda, gmr_sstep,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::PlatformStream<cudaStream_t>>()
                                  .Arg<ffi::AnyBuffer>()  // idx
                                  .Arg<ffi::AnyBuffer>()  // eps
                                  .Arg<ffi::AnyBuffer>()  // c1
                                  .Arg<ffi::AnyBuffer>()  // c2
                                  .Arg<ffi::AnyBuffer>()  // xn
                                  .Arg<ffi::AnyBuffer>()  // xe
                                  .Arg<ffi::AnyBuffer>()  // sig
                                  .Arg<ffi::AnyBuffer>()  // tgt
                                  .Arg<ffi::AnyBuffer>()  // prc
                                  .Arg<ffi::AnyBuffer>()  // K
                                  .Arg<ffi::AnyBuffer>()  // wt
                                  .Arg<ffi::AnyBuffer>()  // logdet
                                  .Arg<ffi::AnyBuffer>()  // scale
                                  .Arg<ffi::AnyBuffer>()  // theta0
                                  .Arg<ffi::AnyBuffer>()  // program
                                  .Arg<ffi::AnyBuffer>()  // floats
                                  .Ret<ffi::AnyBuffer>()  // theta
                                  .Ret<ffi::AnyBuffer>()  // m
                                  .Ret<ffi::AnyBuffer>()  // v
                                  .Ret<ffi::AnyBuffer>()  // stats
                                  .Ret<ffi::AnyBuffer>()  // cycles
                                  .Ret<ffi::AnyBuffer>()  // form
                                  .Attr<int64_t>("steps")
                                  .Attr<int64_t>("smem_bytes")
                                  .Attr<int64_t>("form"));
