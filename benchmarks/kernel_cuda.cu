// The floor of a hand-written CUDA S-step: dependent products and a grid-wide Adam update.
//
// Built and run by benchmarks/kernel_cuda.py (nvcc for the GPU at hand); prints one JSON object
// per line. These kernels, each checked against a double-precision host reference before it is
// timed:
//
//   chain_fma   one thread block of 256 threads; the loop body is `chain` dependent products
//               h <- leaky_relu(h W) of h [32, 64] by W [64, 64] on the CUDA cores (float32
//               fused multiply-adds, h and W in shared memory, a block barrier per product).
//   chain_mma   the same chain on the tensor cores with warp-level `mma.sync` (m16n8k8, TF32
//               operands, float32 accumulators), one warp per 16 rows, 1 or 3 passes (tf32 or
//               tf32x3: a_lo·b_hi + a_hi·b_lo + a_hi·b_hi). W's rows are stored in the order in
//               which an accumulator fragment is laid out, so that a product's output fragment is
//               the next product's input fragment as it stands: with `nsplit` = 1 a warp holds its
//               rows' activations in registers from product to product, with no shared memory and
//               no barrier. With `nsplit` = 2 or 4 the 64 output columns are split over that many
//               warps, which exchange their fragments through shared memory with a named barrier.
//   chain_cluster the tf32x3 chain over a thread-block cluster of 2, 4 or 8 blocks (sm_90): the
//               columns split over every block's warps, each product's output fragments stored into
//               every block's shared memory, then the cluster's barrier; cluster_adam, Adam over a
//               cluster (grid_adam's work, or each block its own slice's gradient), the cluster's
//               barrier between. Each block of a cluster has a multiprocessor of its own.
//   grid_adam   Adam on n parameters per step, split over a cooperative grid of one block per
//               multiprocessor: block 0 reads the weights and writes a gradient (as the block
//               that forms the step's products would), grid sync, every block updates its slice
//               of (w, m, v) in global memory, grid sync (16-byte loads and stores throughout). Mode "sync" keeps the two syncs alone,
//               mode "block" does the whole update in one block (no grid, no sync).
//   seed_steps  many seeds, one thread block each: per step the tf32x3 chain on weight slots held
//               in shared memory, then Adam over the seed's weights (moments in global memory).
//   chains_mma  2-4 independent chains of chain_mma at once in one block.
//   grid_step, cluster_step, cluster_step_presplit  one seed's steps of seed_steps over a
//               cooperative grid or a cluster (the last with the weights split into TF32 parts once
//               per step): the one-seed designs above timed as one program each, hand-offs included.

#include <cooperative_groups.h>
#include <cuda_runtime.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <random>
#include <string>
#include <vector>

namespace cg = cooperative_groups;

#define CHECK(call)                                                                       \
  do {                                                                                    \
    cudaError_t err_ = (call);                                                            \
    if (err_ != cudaSuccess) {                                                            \
      fprintf(stderr, "CUDA error: %s (%s:%d)\n", cudaGetErrorString(err_), __FILE__, __LINE__); \
      exit(1);                                                                            \
    }                                                                                     \
  } while (0)

constexpr int ROWS = 32;   // the minibatch's 20 rows padded to two 16-row tiles
constexpr int WIDTH = 64;  // the networks' hidden width
constexpr float SLOPE = 0.2f;

__device__ __forceinline__ float leaky(float v) { return v > 0.f ? v : SLOPE * v; }

// ----------------------------------------------------------------------------------------------
// CUDA cores: thread (ty, tx) = (tid / 16, tid % 16) computes rows 2ty, 2ty+1 and columns
// 4tx .. 4tx+3.
__global__ void __launch_bounds__(256) chain_fma(const float* __restrict__ h0, const float* __restrict__ w,
                                                 float* __restrict__ out, int steps, int chain) {
  __shared__ __align__(16) float W[WIDTH][WIDTH];
  __shared__ __align__(16) float H[2][ROWS][WIDTH + 4];
  const int tid = threadIdx.x;
  for (int i = tid; i < WIDTH * WIDTH; i += blockDim.x) W[i / WIDTH][i % WIDTH] = w[i];
  for (int i = tid; i < ROWS * WIDTH; i += blockDim.x) H[0][i / WIDTH][i % WIDTH] = h0[i];
  __syncthreads();
  const int ty = tid / 16, tx = tid % 16;
  int cur = 0;
  for (int s = 0; s < steps; ++s) {
    for (int c = 0; c < chain; ++c) {
      float acc[2][4] = {};
#pragma unroll 16
      for (int k = 0; k < WIDTH; ++k) {
        const float a0 = H[cur][2 * ty][k], a1 = H[cur][2 * ty + 1][k];
        const float4 b = *reinterpret_cast<const float4*>(&W[k][4 * tx]);
        acc[0][0] = fmaf(a0, b.x, acc[0][0]);
        acc[0][1] = fmaf(a0, b.y, acc[0][1]);
        acc[0][2] = fmaf(a0, b.z, acc[0][2]);
        acc[0][3] = fmaf(a0, b.w, acc[0][3]);
        acc[1][0] = fmaf(a1, b.x, acc[1][0]);
        acc[1][1] = fmaf(a1, b.y, acc[1][1]);
        acc[1][2] = fmaf(a1, b.z, acc[1][2]);
        acc[1][3] = fmaf(a1, b.w, acc[1][3]);
      }
#pragma unroll
      for (int r = 0; r < 2; ++r) {
        float4 o = make_float4(leaky(acc[r][0]), leaky(acc[r][1]), leaky(acc[r][2]), leaky(acc[r][3]));
        *reinterpret_cast<float4*>(&H[cur ^ 1][2 * ty + r][4 * tx]) = o;
      }
      __syncthreads();
      cur ^= 1;
    }
  }
  for (int i = tid; i < ROWS * WIDTH; i += blockDim.x) out[i] = H[cur][i / WIDTH][i % WIDTH];
}

// ----------------------------------------------------------------------------------------------
// Tensor cores. Fragments of mma.m16n8k8 (TF32), lane = 4g + t:
//   A (16x8): a0 (g, t), a1 (g+8, t), a2 (g, t+4), a3 (g+8, t+4)
//   B (8x8):  b0 (k=t, n=g), b1 (k=t+4, n=g)
//   C (16x8): c0 (g, 2t), c1 (g, 2t+1), c2 (g+8, 2t), c3 (g+8, 2t+1)
// Take the k-step kk's local column t to be activation column 8kk+2t and local column t+4 to be
// 8kk+2t+1 (a permutation of the summed index, applied to W's rows alike): then the A fragment of
// k-step kk is (c0, c2, c1, c3) of the previous product's n-tile kk, in the same lane.

__device__ __forceinline__ uint32_t to_tf32(float x) {
  uint32_t r;
  asm("cvt.rna.tf32.f32 %0, %1;" : "=r"(r) : "f"(x));
  return r;
}

__device__ __forceinline__ void mma_tf32(float (&d)[4], const uint32_t (&a)[4], uint32_t b0, uint32_t b1) {
  asm("mma.sync.aligned.m16n8k8.row.col.f32.tf32.tf32.f32 {%0,%1,%2,%3}, {%4,%5,%6,%7}, {%8,%9}, "
      "{%0,%1,%2,%3};"
      : "+f"(d[0]), "+f"(d[1]), "+f"(d[2]), "+f"(d[3])
      : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b0), "r"(b1));
}

// The B fragments of k-step kk and n-tile nn: hi, and (tf32x3) lo, as mma.sync takes them.
struct BFragment {
  uint2 hi, lo;
};

// The TF32 split of two weights into the B fragments' hi and lo parts.
__device__ __forceinline__ BFragment split_b(float v0, float v1) {
  const uint32_t h0b = to_tf32(v0), h1b = to_tf32(v1);
  return {make_uint2(h0b, h1b), make_uint2(to_tf32(v0 - __uint_as_float(h0b)), to_tf32(v1 - __uint_as_float(h1b)))};
}

// How the warps that share a row tile's columns pass their output fragments on: put(nn, v) stores
// this lane's fragment of n-tile nn, sync(frag) waits for every part and loads all 8 fragments.
// Both double-buffer their fragments (`buf` flips at every sync), so that one barrier per product
// suffices: a part writes a buffer again only after every part has passed the barrier that follows
// its reads of it.
// TileExchange: the warps of one block, through its shared memory X, at named barrier 1 + mtile
// (or `barrier`, where several chains share the block).
struct TileExchange {
  float4 (*X)[2][8][32];
  int buf, mtile, lane, threads;
  int barrier = -1;
  __device__ __forceinline__ void put(int nn, float4 v) { X[buf][mtile][nn][lane] = v; }
  __device__ __forceinline__ void sync(float4 (&frag)[8]) {
    asm volatile("bar.sync %0, %1;" ::"r"(barrier >= 0 ? barrier : 1 + mtile), "r"(threads) : "memory");
#pragma unroll
    for (int kk = 0; kk < 8; ++kk) frag[kk] = X[buf][mtile][kk][lane];
    buf ^= 1;
  }
};

// ClusterExchange: the blocks of a thread-block cluster (Hopper), each fragment stored into X of
// every block of the cluster (distributed shared memory; ranks[r] is block r's X, this block's
// included), then the cluster's barrier (release / acquire), then this block's X read.
template <int CLUSTER>
struct ClusterExchange {
  float4 (*X)[2][8][32];
  float4 (*ranks[CLUSTER])[2][8][32];
  int buf, mtile, lane;
  __device__ __forceinline__ void put(int nn, float4 v) {
#pragma unroll
    for (int r = 0; r < CLUSTER; ++r) ranks[r][buf][mtile][nn][lane] = v;
  }
  __device__ __forceinline__ void sync(float4 (&frag)[8]) {
    cg::this_cluster().sync();
#pragma unroll
    for (int kk = 0; kk < 8; ++kk) frag[kk] = X[buf][mtile][kk][lane];
    buf ^= 1;
  }
};

// `chain` dependent products frag <- leaky(frag W_c) of one warp's share of one 16-row tile, on the
// tensor cores; fetch(c, kk, nn) gives W_c's B fragment (kk, nn) for this lane. The 64 columns are
// split into PARTS parts of 8 / PARTS n-tiles (this warp's: `part`); with PARTS > 1 the parts pass
// their output fragments on through `exchange` (TileExchange or ClusterExchange).
// ACCS = 3 (with PASSES = 3): each pass into an accumulator of its own, added at the end, so that
// an accumulator's chain of dependent mma.sync is 8 long instead of 24.
template <int PASSES, int PARTS, int ACCS, class Fetch, class Exchange>
__device__ __forceinline__ void product_chain(float4 (&frag)[8], Exchange& exchange, int part, int chain,
                                              const Fetch& fetch) {
  constexpr int NT = 8 / PARTS;  // n-tiles per warp
  static_assert(ACCS == 1 || (ACCS == 3 && PASSES == 3), "one accumulator, or one per pass of three");
  float acc[ACCS][NT][4];
  for (int c = 0; c < chain; ++c) {
#pragma unroll
    for (int a = 0; a < ACCS; ++a)
#pragma unroll
      for (int j = 0; j < NT; ++j) acc[a][j][0] = acc[a][j][1] = acc[a][j][2] = acc[a][j][3] = 0.f;
#pragma unroll
    for (int kk = 0; kk < 8; ++kk) {
      const float4 f = frag[kk];
      const uint32_t ahi[4] = {to_tf32(f.x), to_tf32(f.y), to_tf32(f.z), to_tf32(f.w)};
      uint32_t alo[4];
      if (PASSES == 3) {
        alo[0] = to_tf32(f.x - __uint_as_float(ahi[0]));
        alo[1] = to_tf32(f.y - __uint_as_float(ahi[1]));
        alo[2] = to_tf32(f.z - __uint_as_float(ahi[2]));
        alo[3] = to_tf32(f.w - __uint_as_float(ahi[3]));
      }
#pragma unroll
      for (int j = 0; j < NT; ++j) {
        const BFragment b = fetch(c, kk, part * NT + j);
        if (PASSES == 3) {
          mma_tf32(acc[0][j], alo, b.hi.x, b.hi.y);
          mma_tf32(acc[ACCS == 3 ? 1 : 0][j], ahi, b.lo.x, b.lo.y);
        }
        mma_tf32(acc[ACCS == 3 ? 2 : 0][j], ahi, b.hi.x, b.hi.y);
      }
    }
    if (ACCS == 3) {
#pragma unroll
      for (int j = 0; j < NT; ++j)
#pragma unroll
        for (int e = 0; e < 4; ++e) acc[0][j][e] = (acc[0][j][e] + acc[1 % ACCS][j][e]) + acc[2 % ACCS][j][e];
    }
    if (PARTS == 1) {
#pragma unroll
      for (int j = 0; j < NT; ++j)
        frag[j] = make_float4(leaky(acc[0][j][0]), leaky(acc[0][j][2]), leaky(acc[0][j][1]), leaky(acc[0][j][3]));
    } else {
#pragma unroll
      for (int j = 0; j < NT; ++j)
        exchange.put(part * NT + j,
                     make_float4(leaky(acc[0][j][0]), leaky(acc[0][j][2]), leaky(acc[0][j][1]), leaky(acc[0][j][3])));
      exchange.sync(frag);
    }
  }
}

// A warp's rows' A fragments for all 8 k-steps from h [ROWS, WIDTH] (row-major), and back.
__device__ __forceinline__ void load_fragments(float4 (&frag)[8], const float* __restrict__ h, int r0, int t) {
#pragma unroll
  for (int kk = 0; kk < 8; ++kk)
    frag[kk] = make_float4(h[r0 * WIDTH + 8 * kk + 2 * t], h[(r0 + 8) * WIDTH + 8 * kk + 2 * t],
                           h[r0 * WIDTH + 8 * kk + 2 * t + 1], h[(r0 + 8) * WIDTH + 8 * kk + 2 * t + 1]);
}

// the last product's output: frag[kk] = (c0, c2, c1, c3) of n-tile kk
__device__ __forceinline__ void store_fragments(const float4 (&frag)[8], float* __restrict__ out, int r0, int t) {
#pragma unroll
  for (int kk = 0; kk < 8; ++kk) {
    out[r0 * WIDTH + 8 * kk + 2 * t] = frag[kk].x;
    out[r0 * WIDTH + 8 * kk + 2 * t + 1] = frag[kk].z;
    out[(r0 + 8) * WIDTH + 8 * kk + 2 * t] = frag[kk].y;
    out[(r0 + 8) * WIDTH + 8 * kk + 2 * t + 1] = frag[kk].w;
  }
}

// W [64, 64] (row-major [k][o]) into the B fragments (hi, and lo for PASSES = 3) per (kk, nn, lane).
template <int PASSES>
__device__ __forceinline__ void load_b_fragments(uint2 (*Bhi)[8][32], uint2 (*Blo)[8][32], const float* __restrict__ w) {
  for (int i = threadIdx.x; i < 8 * 8 * 32; i += blockDim.x) {
    const int kk = i / 256, nn = (i / 32) % 8, l = i % 32, lg = l / 4, lt = l % 4;
    const BFragment b = split_b(w[(8 * kk + 2 * lt) * WIDTH + 8 * nn + lg], w[(8 * kk + 2 * lt + 1) * WIDTH + 8 * nn + lg]);
    Bhi[kk][nn][l] = b.hi;
    if (PASSES == 3) Blo[kk][nn][l] = b.lo;
  }
}

template <int PASSES, int NSPLIT, int ACCS>
__global__ void __launch_bounds__(64 * NSPLIT) chain_mma(const float* __restrict__ h0, const float* __restrict__ w,
                                                         float* __restrict__ out, int steps, int chain) {
  // B fragments (hi, lo) per (kk, nn, lane): (b0, b1)
  __shared__ __align__(16) uint2 Bhi[8][8][32];
  __shared__ __align__(16) uint2 Blo[PASSES == 3 ? 8 : 1][8][32];
  // exchanged A fragments, double-buffered: [buffer][m-tile][kk][lane]
  __shared__ __align__(16) float4 X[NSPLIT > 1 ? 2 : 1][2][8][32];
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32;
  const int g = lane / 4, t = lane % 4;
  const int mtile = warp / NSPLIT, part = warp % NSPLIT;
  load_b_fragments<PASSES>(Bhi, Blo, w);
  float4 frag[8];
  const int r0 = 16 * mtile + g;
  load_fragments(frag, h0, r0, t);
  __syncthreads();
  TileExchange exchange{NSPLIT > 1 ? X : nullptr, 0, mtile, lane, 32 * NSPLIT};
  const auto fetch = [&](int, int kk, int nn) {
    return BFragment{Bhi[kk][nn][lane], PASSES == 3 ? Blo[kk][nn][lane] : make_uint2(0u, 0u)};
  };
  for (int s = 0; s < steps; ++s) product_chain<PASSES, NSPLIT, ACCS>(frag, exchange, part, chain, fetch);
  if (part == 0) store_fragments(frag, out, r0, t);
}

// CHAINS independent tf32x3 chains (three accumulators) at once in one block, each on its own
// 2·NSPLIT warps with its own exchange buffers and named barriers and chain_mma's shared B
// fragments; chain i writes its output at out + i·ROWS·WIDTH. A GMR step's products are not all
// one chain: the decoder and the translation network run side by side, and a layer's weight
// gradient is off the path of the input gradients. Whether such products cost a dependent
// product's time each, or overlap, is what this kernel times (µs per product of each chain).
template <int NSPLIT, int CHAINS>
__global__ void __launch_bounds__(64 * NSPLIT * CHAINS) chains_mma(const float* __restrict__ h0, const float* __restrict__ w,
                                                                   float* __restrict__ out, int steps, int chain) {
  static_assert(NSPLIT > 1 && 1 + 2 * CHAINS <= 16, "named barriers 1 .. 2·CHAINS");
  __shared__ __align__(16) uint2 Bhi[8][8][32];
  __shared__ __align__(16) uint2 Blo[8][8][32];
  extern __shared__ float4 chain_exchange[];  // [CHAINS][2][2][8][32]
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32;
  const int g = lane / 4, t = lane % 4;
  const int c = warp / (2 * NSPLIT), local = warp % (2 * NSPLIT);
  const int mtile = local / NSPLIT, part = local % NSPLIT;
  load_b_fragments<3>(Bhi, Blo, w);
  float4 frag[8];
  const int r0 = 16 * mtile + g;
  load_fragments(frag, h0, r0, t);
  __syncthreads();
  auto* X = reinterpret_cast<float4 (*)[2][8][32]>(chain_exchange + c * (2 * 2 * 8 * 32));
  TileExchange exchange{X, 0, mtile, lane, 32 * NSPLIT, 1 + 2 * c + mtile};
  const auto fetch = [&](int, int kk, int nn) { return BFragment{Bhi[kk][nn][lane], Blo[kk][nn][lane]}; };
  for (int s = 0; s < steps; ++s) product_chain<3, NSPLIT, 3>(frag, exchange, part, chain, fetch);
  if (part == 0) store_fragments(frag, out + c * ROWS * WIDTH, r0, t);
}

// The multiprocessor each block of the last cluster launch ran on (block rank r: cluster_sm[r]),
// so that the host can check that a cluster's blocks had multiprocessors of their own.
__device__ int cluster_sm[8];

__device__ __forceinline__ void record_sm(int rank) {
  if (threadIdx.x == 0) {
    int sm;
    asm volatile("mov.u32 %0, %%smid;" : "=r"(sm));
    cluster_sm[rank] = sm;
  }
}

// The tf32x3 chain (three accumulators) over a thread-block cluster of CLUSTER blocks of NSPLIT
// warps per row tile: the 64 columns in CLUSTER·NSPLIT parts, block r's warps computing parts
// r·NSPLIT .. r·NSPLIT + NSPLIT − 1 with more multiprocessors' tensor cores, and every product's
// output fragments stored into every block's shared memory before the cluster's barrier
// (ClusterExchange). Block 0 writes the result.
template <int CLUSTER, int NSPLIT>
__global__ void __launch_bounds__(64 * NSPLIT) chain_cluster(const float* __restrict__ h0, const float* __restrict__ w,
                                                             float* __restrict__ out, int steps, int chain) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900  // clusters need sm_90 (as cluster_adam)
  __shared__ __align__(16) uint2 Bhi[8][8][32];
  __shared__ __align__(16) uint2 Blo[8][8][32];
  __shared__ __align__(16) float4 X[2][2][8][32];
  cg::cluster_group cluster = cg::this_cluster();
  const int rank = int(cluster.block_rank());
  record_sm(rank);
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32;
  const int g = lane / 4, t = lane % 4;
  const int mtile = warp / NSPLIT, part = rank * NSPLIT + warp % NSPLIT;
  load_b_fragments<3>(Bhi, Blo, w);
  float4 frag[8];
  const int r0 = 16 * mtile + g;
  load_fragments(frag, h0, r0, t);
  ClusterExchange<CLUSTER> exchange;
  exchange.X = X;
  exchange.buf = 0;
  exchange.mtile = mtile;
  exchange.lane = lane;
#pragma unroll
  for (int r = 0; r < CLUSTER; ++r) exchange.ranks[r] = cluster.map_shared_rank(X, r);
  cluster.sync();  // every block of the cluster has started and loaded its fragments
  const auto fetch = [&](int, int kk, int nn) { return BFragment{Bhi[kk][nn][lane], Blo[kk][nn][lane]}; };
  for (int s = 0; s < steps; ++s) product_chain<3, CLUSTER * NSPLIT, 3>(frag, exchange, part, chain, fetch);
  if (rank == 0 && warp % NSPLIT == 0) store_fragments(frag, out, r0, t);
#endif
}

// ----------------------------------------------------------------------------------------------
// Hopper's warpgroup products (wgmma.mma_async m64n64k8, TF32 operands, float32 accumulators): the
// same chain with one warpgroup (4 warps, 64 rows: the chain's 32, the minibatch's 20 padded, and
// the other two warps' rows zero), A from registers in the same permuted fragments as chain_mma, B in
// shared memory. Built only for sm_90a (kernel_cuda.py defines KERNEL_CUDA_WGMMA there).
#ifdef KERNEL_CUDA_WGMMA
// B of k-step kk, K-major, in core matrices of 8 columns × 4 k (16-byte rows), no swizzle: core
// (kc, nc) at 128·kc + 256·nc bytes, inside it n_local·16 + k_local·4 bytes; k_local holds W's row
// 8kk + 2·k_local (k_local < 4) or 8kk + 2·(k_local − 4) + 1, the A fragments' column order.
__device__ __forceinline__ uint64_t b_descriptor(const void* p) {
  const uint32_t addr = static_cast<uint32_t>(__cvta_generic_to_shared(p));
  return uint64_t((addr & 0x3FFFF) >> 4) | (uint64_t(128 >> 4) << 16) | (uint64_t(256 >> 4) << 32);
}

__device__ __forceinline__ void wgmma_tf32(float (&d)[32], const uint32_t (&a)[4], uint64_t b, int accumulate) {
  asm volatile(
      "{\n.reg .pred p;\nsetp.ne.b32 p, %37, 0;\n"
      "wgmma.mma_async.sync.aligned.m64n64k8.f32.tf32.tf32 "
      "{%0,%1,%2,%3,%4,%5,%6,%7,%8,%9,%10,%11,%12,%13,%14,%15,%16,%17,%18,%19,%20,%21,%22,%23,%24,%25,%26,%27,"
      "%28,%29,%30,%31}, {%32,%33,%34,%35}, %36, p, 1, 1;\n}\n"
      : "+f"(d[0]), "+f"(d[1]), "+f"(d[2]), "+f"(d[3]), "+f"(d[4]), "+f"(d[5]), "+f"(d[6]), "+f"(d[7]), "+f"(d[8]),
        "+f"(d[9]), "+f"(d[10]), "+f"(d[11]), "+f"(d[12]), "+f"(d[13]), "+f"(d[14]), "+f"(d[15]), "+f"(d[16]),
        "+f"(d[17]), "+f"(d[18]), "+f"(d[19]), "+f"(d[20]), "+f"(d[21]), "+f"(d[22]), "+f"(d[23]), "+f"(d[24]),
        "+f"(d[25]), "+f"(d[26]), "+f"(d[27]), "+f"(d[28]), "+f"(d[29]), "+f"(d[30]), "+f"(d[31])
      : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "l"(b), "r"(accumulate));
}

template <int PASSES, int ACCS>
__global__ void __launch_bounds__(128) chain_wgmma(const float* __restrict__ h0, const float* __restrict__ w,
                                                   float* __restrict__ out, int steps, int chain) {
  static_assert(ACCS == 1 || (ACCS == 3 && PASSES == 3), "one accumulator, or one per pass of three");
  __shared__ __align__(128) uint32_t Bhi[8][512];
  __shared__ __align__(128) uint32_t Blo[PASSES == 3 ? 8 : 1][512];
  for (int i = threadIdx.x; i < 8 * 512; i += blockDim.x) {
    const int kk = i / 512, r = i % 512;
    const int nc = r / 64, kc = (r % 64) / 32, n_local = (r % 32) / 4, k_local = 4 * kc + r % 4;
    const int row = 8 * kk + (k_local < 4 ? 2 * k_local : 2 * (k_local - 4) + 1);
    const BFragment b = split_b(w[row * WIDTH + 8 * nc + n_local], 0.f);
    Bhi[kk][r] = b.hi.x;
    if (PASSES == 3) Blo[kk][r] = b.lo.x;
  }
  // wgmma reads B through the async proxy: make the ordinary stores above visible to it
  asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory");
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32, t = lane % 4;
  const int r0 = 16 * warp + lane / 4;
  float4 frag[8];
  if (warp < 2) load_fragments(frag, h0, r0, t);
  else
    for (int kk = 0; kk < 8; ++kk) frag[kk] = make_float4(0.f, 0.f, 0.f, 0.f);  // the padding rows
  __syncthreads();
  float d[32], d1[32], d2[32];
  for (int s = 0; s < steps; ++s)
    for (int c = 0; c < chain; ++c) {
      uint32_t ahi[8][4], alo[8][4];
#pragma unroll
      for (int kk = 0; kk < 8; ++kk) {
        const float f[4] = {frag[kk].x, frag[kk].y, frag[kk].z, frag[kk].w};
#pragma unroll
        for (int e = 0; e < 4; ++e) {
          ahi[kk][e] = to_tf32(f[e]);
          alo[kk][e] = PASSES == 3 ? to_tf32(f[e] - __uint_as_float(ahi[kk][e])) : 0u;
        }
      }
      asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory");
#pragma unroll
      for (int kk = 0; kk < 8; ++kk) {
        if constexpr (PASSES == 3 && ACCS == 3) {
          wgmma_tf32(d, alo[kk], b_descriptor(Bhi[kk]), kk > 0);
          wgmma_tf32(d1, ahi[kk], b_descriptor(Blo[kk]), kk > 0);
          wgmma_tf32(d2, ahi[kk], b_descriptor(Bhi[kk]), kk > 0);
        } else if constexpr (PASSES == 3) {
          wgmma_tf32(d, alo[kk], b_descriptor(Bhi[kk]), kk > 0);
          wgmma_tf32(d, ahi[kk], b_descriptor(Blo[kk]), 1);
          wgmma_tf32(d, ahi[kk], b_descriptor(Bhi[kk]), 1);
        } else {
          wgmma_tf32(d, ahi[kk], b_descriptor(Bhi[kk]), kk > 0);
        }
      }
      asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory");
      asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory");
      if constexpr (ACCS == 3) {
#pragma unroll
        for (int i = 0; i < 32; ++i) d[i] = (d[i] + d1[i]) + d2[i];
      }
      // accumulator register 4j + (0, 1, 2, 3) is (row g, col 8j + 2t), (g, 8j + 2t + 1), (g + 8, 8j + 2t),
      // (g + 8, 8j + 2t + 1), the c0..c3 of mma.sync's n-tile j: the next A fragments as in chain_mma
#pragma unroll
      for (int j = 0; j < 8; ++j)
        frag[j] = make_float4(leaky(d[4 * j]), leaky(d[4 * j + 2]), leaky(d[4 * j + 1]), leaky(d[4 * j + 3]));
    }
  if (warp < 2) store_fragments(frag, out, r0, t);
}
#endif

// ----------------------------------------------------------------------------------------------
// Adam on n parameters per step. The gradient stands for what the step's products would give:
// g = 1e-3·|w| + 1e-4, read from the weights so that each step depends on the last, and never near
// zero: where g crosses zero Adam's update g / (|g| + eps) turns on float32's rounding of g alone,
// beyond the update's error bound (adam_bound in kernel_cuda.py).
struct AdamArgs {
  float* w;
  float* m;
  float* v;
  float* g;
  int n;
  int steps;
  float lr, b1, b2, eps;
};

__device__ __forceinline__ float synthetic_gradient(float w) { return 1e-3f * fabsf(w) + 1e-4f; }

// the gradient of four weights in a whole-step kernel: synthetic_gradient plus h, the chain's link
__device__ __forceinline__ float4 synthetic_quad(float4 w, float h) {
  return make_float4(synthetic_gradient(w.x) + h, synthetic_gradient(w.y) + h, synthetic_gradient(w.z) + h,
                     synthetic_gradient(w.w) + h);
}

__device__ __forceinline__ float correction(float beta, int step) { return 1.f / (1.f - powf(beta, float(step + 1))); }

__device__ __forceinline__ float adam_one(float& w, float& m, float& v, float g, float c1, float c2, const AdamArgs& a) {
  m = a.b1 * m + (1.f - a.b1) * g;
  v = a.b2 * v + (1.f - a.b2) * g * g;
  w -= a.lr * (m * c1) / (sqrtf(v * c2) + a.eps);
  return w;
}

// entries 4i .. 4i+3 (16-byte loads and stores: n is a multiple of 4)
// four entries' Adam update in registers
__device__ __forceinline__ void adam_four(float4& w, float4& m, float4& v, float4 g, float c1, float c2,
                                          const AdamArgs& a) {
  adam_one(w.x, m.x, v.x, g.x, c1, c2, a);
  adam_one(w.y, m.y, v.y, g.y, c1, c2, a);
  adam_one(w.z, m.z, v.z, g.z, c1, c2, a);
  adam_one(w.w, m.w, v.w, g.w, c1, c2, a);
}

__device__ __forceinline__ void adam_quad(const AdamArgs& a, int i, float c1, float c2) {
  const float4 g = reinterpret_cast<const float4*>(a.g)[i];
  float4 w = reinterpret_cast<float4*>(a.w)[i], m = reinterpret_cast<float4*>(a.m)[i],
         v = reinterpret_cast<float4*>(a.v)[i];
  adam_four(w, m, v, g, c1, c2, a);
  reinterpret_cast<float4*>(a.w)[i] = w;
  reinterpret_cast<float4*>(a.m)[i] = m;
  reinterpret_cast<float4*>(a.v)[i] = v;
}

__device__ __forceinline__ void gradient_quad(const AdamArgs& a, int i) {
  const float4 w = reinterpret_cast<const float4*>(a.w)[i];
  reinterpret_cast<float4*>(a.g)[i] =
      make_float4(synthetic_gradient(w.x), synthetic_gradient(w.y), synthetic_gradient(w.z), synthetic_gradient(w.w));
}

// mode 0: the grid's two syncs alone; mode 1: gradient in block 0, sync, Adam over the grid, sync
__global__ void grid_adam(AdamArgs a, int mode) {
  cg::grid_group grid = cg::this_grid();
  const int quads = a.n / 4;
  const int per_block = (quads + gridDim.x - 1) / gridDim.x;
  const int lo = blockIdx.x * per_block, hi = min(quads, lo + per_block);
  for (int s = 0; s < a.steps; ++s) {
    if (mode == 1 && blockIdx.x == 0)
      for (int i = threadIdx.x; i < quads; i += blockDim.x) gradient_quad(a, i);
    grid.sync();
    if (mode == 1) {
      const float c1 = correction(a.b1, s), c2 = correction(a.b2, s);
      for (int i = lo + threadIdx.x; i < hi; i += blockDim.x) adam_quad(a, i, c1, c2);
    }
    grid.sync();
  }
}

// the whole update in one block
__global__ void block_adam(AdamArgs a) {
  const int quads = a.n / 4;
  for (int s = 0; s < a.steps; ++s) {
    const float c1 = correction(a.b1, s), c2 = correction(a.b2, s);
    for (int i = threadIdx.x; i < quads; i += blockDim.x) {
      gradient_quad(a, i);
      adam_quad(a, i, c1, c2);
    }
    __syncthreads();
  }
}

// Adam over one thread-block cluster of CLUSTER blocks: one seed's update spread over CLUSTER
// multiprocessors with the cluster's barrier, where grid_adam spreads it over the whole GPU with the
// grid's. Mode 0: the barrier alone, once per step. Mode 1: grid_adam's work: block 0 writes the
// gradient of every entry (as the block that forms the products would), barrier, every block
// updates its slice, barrier. Mode 2: every block writes the gradient of its own slice and updates
// it, one barrier (as when the cluster's blocks form the products, each its columns' weight
// gradient). Clusters need sm_90: built empty for older targets, and the host runs them only on such
// a GPU.
template <int CLUSTER>
__global__ void cluster_adam(AdamArgs a, int mode) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  cg::cluster_group cluster = cg::this_cluster();
  const int rank = int(cluster.block_rank());
  record_sm(rank);
  const int quads = a.n / 4;
  const int per_block = (quads + CLUSTER - 1) / CLUSTER;
  const int lo = rank * per_block, hi = min(quads, lo + per_block);
  for (int s = 0; s < a.steps; ++s) {
    const float c1 = correction(a.b1, s), c2 = correction(a.b2, s);
    if (mode == 1) {
      if (rank == 0)
        for (int i = threadIdx.x; i < quads; i += blockDim.x) gradient_quad(a, i);
      cluster.sync();
      for (int i = lo + threadIdx.x; i < hi; i += blockDim.x) adam_quad(a, i, c1, c2);
    } else if (mode == 2) {
      for (int i = lo + threadIdx.x; i < hi; i += blockDim.x) {
        gradient_quad(a, i);
        adam_quad(a, i, c1, c2);
      }
    }
    cluster.sync();
  }
#endif
}

// A thread's place in a whole-step kernel's chain: its warp, its lane's group g and place t in the
// group, its warp's row tile and column part, and its first row.
template <int NSPLIT>
struct ChainPlace {
  int lane = threadIdx.x % 32, warp = threadIdx.x / 32, g = lane / 4, t = lane % 4;
  int mtile = warp / NSPLIT, part = warp % NSPLIT, r0 = 16 * mtile + g;
};

// B fragments from weights in shared memory in seed_steps' slot order, split into TF32 parts as
// they are read (the weights change every step): product c uses slot (first_slot + c) % slots.
struct SlotFetch {
  const float* w;
  int first_slot, slots, lane;
  __device__ __forceinline__ BFragment operator()(int c, int kk, int nn) const {
    const float2 b =
        reinterpret_cast<const float2*>(w + ((first_slot + c) % slots) * WIDTH * WIDTH)[(kk * 8 + nn) * 32 + lane];
    return split_b(b.x, b.y);
  }
};

// A whole-step kernel's chain, run by its chain warps: from the input rows h (each step starts
// from them, as a minibatch does), `products` dependent products, and warp 0's first entry into
// `link`, which the step's gradient waits on.
template <int NSPLIT, class Fetch>
__device__ __forceinline__ void step_chain(float4 (&frag)[8], TileExchange& exchange, const float* __restrict__ h,
                                           const ChainPlace<NSPLIT>& at, int products, const Fetch& fetch, float& link) {
  load_fragments(frag, h, at.r0, at.t);
  product_chain<3, NSPLIT, 3>(frag, exchange, at.part, products, fetch);
  if (threadIdx.x == 0) link = frag[0].x;
}

// ----------------------------------------------------------------------------------------------
// Many seeds, one thread block each, `steps` whole steps per launch: per step `products` dependent
// products of the seed's 32 input rows (h0, read again at every step's start) on the tensor cores
// (tf32x3, three accumulators, the columns over NSPLIT warps per row tile), product c on weight
// slot (first_slot + c) % slots, then Adam over all n of the
// seed's weights. The weights stay in shared memory for the whole launch (n floats, each 64 x 64
// slot stored in B-fragment order: entry ((kk·8 + nn)·32 + lane)·2 + j is W[8kk + 2t + j][8nn + g],
// so that a lane's two B values are one 8-byte load without bank conflicts); the moments are in
// global memory, read and written once per step. The weights change every step, so each product
// splits its B fragments into TF32 hi and lo parts as it loads them. The gradient stands for what
// the step's products give: synthetic_gradient(w) + coupling·h, h one entry of the chain's last
// output, so that the update waits for the products (a barrier) as a real step's would.
template <int NSPLIT, int THREADS>
__global__ void __launch_bounds__(THREADS) seed_steps(const float* __restrict__ h0, const float* __restrict__ w0,
                                                  float* __restrict__ w_out, float* __restrict__ m,
                                                  float* __restrict__ v, float* __restrict__ out, float*, int n,
                                                  int steps, int products, int first_slot, float coupling, float lr,
                                                  float b1, float b2, float eps) {
  extern __shared__ float4 shared_w4[];
  float* w = reinterpret_cast<float*>(shared_w4);
  __shared__ __align__(16) float4 X[NSPLIT > 1 ? 2 : 1][2][8][32];
  __shared__ float link;
  const int seed = blockIdx.x, quads = n / 4, slots = n / (WIDTH * WIDTH);
  const float4* w0_4 = reinterpret_cast<const float4*>(w0 + size_t(seed) * n);
  float4* m4 = reinterpret_cast<float4*>(m + size_t(seed) * n);
  float4* v4 = reinterpret_cast<float4*>(v + size_t(seed) * n);
  for (int i = threadIdx.x; i < quads; i += blockDim.x) shared_w4[i] = w0_4[i];
  const ChainPlace<NSPLIT> at;
  const bool chain_warp = at.warp < 2 * NSPLIT;
  const float* h_seed = h0 + size_t(seed) * ROWS * WIDTH;
  float4 frag[8];
  __syncthreads();
  TileExchange exchange{NSPLIT > 1 ? X : nullptr, 0, at.mtile, at.lane, 32 * NSPLIT};
  const SlotFetch fetch{w, first_slot, slots, at.lane};
  for (int s = 0; s < steps; ++s) {
    if (chain_warp) {
      step_chain<NSPLIT>(frag, exchange, h_seed, at, products, fetch, link);
    }
    __syncthreads();
    const float h = coupling * link;
    const float c1 = correction(b1, s), c2 = correction(b2, s);
    const AdamArgs a{nullptr, nullptr, nullptr, nullptr, n, steps, lr, b1, b2, eps};
    for (int i = threadIdx.x; i < quads; i += blockDim.x) {
      float4 wq = shared_w4[i], mq = m4[i], vq = v4[i];
      const float4 g = synthetic_quad(wq, h);
      adam_four(wq, mq, vq, g, c1, c2, a);
      shared_w4[i] = wq;
      m4[i] = mq;
      v4[i] = vq;
    }
    __syncthreads();
  }
  float4* w_out4 = reinterpret_cast<float4*>(w_out + size_t(seed) * n);
  for (int i = threadIdx.x; i < quads; i += blockDim.x) w_out4[i] = shared_w4[i];
  if (chain_warp && at.part == 0) store_fragments(frag, out + size_t(seed) * ROWS * WIDTH, at.r0, at.t);
}

// ----------------------------------------------------------------------------------------------
// One seed's whole steps in one launch, spread over more than one multiprocessor (seed_steps'
// arguments; `g`: n floats of global scratch for the gradient). The step of seed_steps — the
// chain's `products` dependent products from the input rows, then Adam over all n weights with
// the gradient synthetic_gradient(w) + coupling·h — with the one-seed designs whose parts
// chain_mma, grid_adam and cluster_adam time apart, so that a step's parts and the hand-offs between
// them are timed as one program:
//   grid_step     a cooperative grid of one block per multiprocessor. The weights live in global
//                 memory (w_out, each block's slice updated by that block). Per step block 0 copies
//                 them into its shared memory, runs the chain on them, writes the whole gradient to
//                 g (as the block that forms a step's products would), grid sync; every block
//                 updates its slice of (w, m, v), grid sync.
//   cluster_step  a thread-block cluster of CLUSTER blocks, each on a multiprocessor of its own. The
//                 weights live in block 0's shared memory for the whole launch; per step block 0 runs
//                 the chain and writes the gradient into its shared memory, cluster barrier; every
//                 block updates its slice, reading and writing w and g in block 0's shared memory
//                 (distributed shared memory) and its moments in global memory, cluster barrier.
// Global memory written by another block is read through L2 (__ldcg), never a stale L1 line.
template <int NSPLIT, int THREADS>
__global__ void __launch_bounds__(THREADS) grid_step(const float* __restrict__ h0, const float* __restrict__ w0,
                                                 float* __restrict__ w_out, float* __restrict__ m,
                                                 float* __restrict__ v, float* __restrict__ out, float* __restrict__ g,
                                                 int n, int steps, int products, int first_slot, float coupling,
                                                 float lr, float b1, float b2, float eps) {
  extern __shared__ float4 shared_w4[];  // block 0: the weights the chain reads
  const float* w = reinterpret_cast<const float*>(shared_w4);
  __shared__ __align__(16) float4 X[NSPLIT > 1 ? 2 : 1][2][8][32];
  __shared__ float link;
  cg::grid_group grid = cg::this_grid();
  const int quads = n / 4, slots = n / (WIDTH * WIDTH);
  const int per_block = (quads + gridDim.x - 1) / gridDim.x;
  const int lo = blockIdx.x * per_block, hi = min(quads, lo + per_block);
  float4* w4 = reinterpret_cast<float4*>(w_out);
  float4* g4 = reinterpret_cast<float4*>(g);
  float4* m4 = reinterpret_cast<float4*>(m);
  float4* v4 = reinterpret_cast<float4*>(v);
  for (int i = lo + threadIdx.x; i < hi; i += blockDim.x) __stcg(w4 + i, reinterpret_cast<const float4*>(w0)[i]);
  const ChainPlace<NSPLIT> at;
  const bool chain_warp = blockIdx.x == 0 && at.warp < 2 * NSPLIT;
  float4 frag[8];
  TileExchange exchange{NSPLIT > 1 ? X : nullptr, 0, at.mtile, at.lane, 32 * NSPLIT};
  const SlotFetch fetch{w, first_slot, slots, at.lane};
  grid.sync();
  for (int s = 0; s < steps; ++s) {
    if (blockIdx.x == 0) {
      for (int i = threadIdx.x; i < quads; i += blockDim.x) shared_w4[i] = __ldcg(w4 + i);
      __syncthreads();
      if (chain_warp) {
        step_chain<NSPLIT>(frag, exchange, h0, at, products, fetch, link);
      }
      __syncthreads();
      const float h = coupling * link;
      for (int i = threadIdx.x; i < quads; i += blockDim.x) {
        const float4 wq = shared_w4[i];
        __stcg(g4 + i, synthetic_quad(wq, h));
      }
    }
    grid.sync();
    const float c1 = correction(b1, s), c2 = correction(b2, s);
    const AdamArgs a{nullptr, nullptr, nullptr, nullptr, n, steps, lr, b1, b2, eps};
    for (int i = lo + threadIdx.x; i < hi; i += blockDim.x) {
      float4 wq = __ldcg(w4 + i), mq = m4[i], vq = v4[i];
      adam_four(wq, mq, vq, __ldcg(g4 + i), c1, c2, a);
      __stcg(w4 + i, wq);
      m4[i] = mq;
      v4[i] = vq;
    }
    grid.sync();
  }
  if (chain_warp && at.part == 0) store_fragments(frag, out, at.r0, at.t);
}

template <int CLUSTER, int NSPLIT, int THREADS>
__global__ void __launch_bounds__(THREADS) cluster_step(const float* __restrict__ h0, const float* __restrict__ w0,
                                                    float* __restrict__ w_out, float* __restrict__ m,
                                                    float* __restrict__ v, float* __restrict__ out, float*, int n,
                                                    int steps, int products, int first_slot, float coupling, float lr,
                                                    float b1, float b2, float eps) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900  // clusters need sm_90
  extern __shared__ float4 shared_w4[];  // block 0: the weights [n / 4], then the gradient [n / 4]
  __shared__ __align__(16) float4 X[NSPLIT > 1 ? 2 : 1][2][8][32];
  __shared__ float link;
  cg::cluster_group cluster = cg::this_cluster();
  const int rank = int(cluster.block_rank());
  record_sm(rank);
  const int quads = n / 4, slots = n / (WIDTH * WIDTH);
  const int per_block = (quads + CLUSTER - 1) / CLUSTER;
  const int lo = rank * per_block, hi = min(quads, lo + per_block);
  float4* w_own = shared_w4;
  float4* g_own = shared_w4 + quads;
  float4* w_zero = cluster.map_shared_rank(w_own, 0);  // block 0's weights and gradient
  float4* g_zero = cluster.map_shared_rank(g_own, 0);
  float4* m4 = reinterpret_cast<float4*>(m);
  float4* v4 = reinterpret_cast<float4*>(v);
  const float* w = reinterpret_cast<const float*>(w_own);
  const ChainPlace<NSPLIT> at;
  const bool chain_warp = rank == 0 && at.warp < 2 * NSPLIT;
  if (rank == 0)
    for (int i = threadIdx.x; i < quads; i += blockDim.x) w_own[i] = reinterpret_cast<const float4*>(w0)[i];
  float4 frag[8];
  TileExchange exchange{NSPLIT > 1 ? X : nullptr, 0, at.mtile, at.lane, 32 * NSPLIT};
  const SlotFetch fetch{w, first_slot, slots, at.lane};
  cluster.sync();
  for (int s = 0; s < steps; ++s) {
    if (rank == 0) {
      if (chain_warp) {
        step_chain<NSPLIT>(frag, exchange, h0, at, products, fetch, link);
      }
      __syncthreads();
      const float h = coupling * link;
      for (int i = threadIdx.x; i < quads; i += blockDim.x) {
        const float4 wq = w_own[i];
        g_own[i] = synthetic_quad(wq, h);
      }
    }
    cluster.sync();
    const float c1 = correction(b1, s), c2 = correction(b2, s);
    const AdamArgs a{nullptr, nullptr, nullptr, nullptr, n, steps, lr, b1, b2, eps};
    for (int i = lo + threadIdx.x; i < hi; i += blockDim.x) {
      float4 wq = w_zero[i], mq = m4[i], vq = v4[i];
      adam_four(wq, mq, vq, g_zero[i], c1, c2, a);
      w_zero[i] = wq;
      m4[i] = mq;
      v4[i] = vq;
    }
    cluster.sync();
  }
  if (rank == 0) {
    for (int i = threadIdx.x; i < quads; i += blockDim.x) reinterpret_cast<float4*>(w_out)[i] = w_own[i];
    if (chain_warp && at.part == 0) store_fragments(frag, out, at.r0, at.t);
  }
#endif
}

// cluster_step with the weights split once per step: the updaters write each weight's TF32 hi and lo
// parts into block 0's shared memory (distributed shared memory) as they update it, so that the
// chain reads its B fragments as they stand (as chain_mma does) instead of splitting them at every
// product. The float32 weights live in global memory (w_out, each block its slice), the gradient too
// (g: block 0 writes all of it, every block reads its slice); block 0's shared memory holds hi [n]
// and lo [n] (uint32, seed_steps' B-fragment order). Block 0 forms the synthetic gradient from
// hi + lo (within 2^-22 of w relative, far below the Adam check's bound), the only float32 weight it
// holds.
template <int CLUSTER, int NSPLIT, int THREADS>
__global__ void __launch_bounds__(THREADS) cluster_step_presplit(const float* __restrict__ h0,
                                                             const float* __restrict__ w0, float* __restrict__ w_out,
                                                             float* __restrict__ m, float* __restrict__ v,
                                                             float* __restrict__ out, float* __restrict__ g, int n,
                                                             int steps, int products, int first_slot, float coupling,
                                                             float lr, float b1, float b2, float eps) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900  // clusters need sm_90
  extern __shared__ uint4 shared_split[];  // block 0: hi [n / 4], then lo [n / 4]
  __shared__ __align__(16) float4 X[NSPLIT > 1 ? 2 : 1][2][8][32];
  __shared__ float link;
  cg::cluster_group cluster = cg::this_cluster();
  const int rank = int(cluster.block_rank());
  record_sm(rank);
  const int quads = n / 4, slots = n / (WIDTH * WIDTH);
  const int per_block = (quads + CLUSTER - 1) / CLUSTER;
  const int lo_q = rank * per_block, hi_q = min(quads, lo_q + per_block);
  uint4* hi_zero = cluster.map_shared_rank(shared_split, 0);
  uint4* lo_zero = hi_zero + quads;
  const uint2* hi2 = reinterpret_cast<const uint2*>(shared_split);
  const uint2* lo2 = reinterpret_cast<const uint2*>(shared_split + quads);
  float4* w4 = reinterpret_cast<float4*>(w_out);
  float4* g4 = reinterpret_cast<float4*>(g);
  float4* m4 = reinterpret_cast<float4*>(m);
  float4* v4 = reinterpret_cast<float4*>(v);
  // each block's slice: the float32 weights to global memory, their split into block 0
  const auto put_split = [&](int i, float4 wq) {
    const BFragment a = split_b(wq.x, wq.y), b = split_b(wq.z, wq.w);
    hi_zero[i] = make_uint4(a.hi.x, a.hi.y, b.hi.x, b.hi.y);
    lo_zero[i] = make_uint4(a.lo.x, a.lo.y, b.lo.x, b.lo.y);
  };
  for (int i = lo_q + threadIdx.x; i < hi_q; i += blockDim.x) w4[i] = reinterpret_cast<const float4*>(w0)[i];
  cluster.sync();  // every block of the cluster has started before any writes into block 0's shared memory
  for (int i = lo_q + threadIdx.x; i < hi_q; i += blockDim.x) put_split(i, w4[i]);
  const ChainPlace<NSPLIT> at;
  const bool chain_warp = rank == 0 && at.warp < 2 * NSPLIT;
  float4 frag[8];
  TileExchange exchange{NSPLIT > 1 ? X : nullptr, 0, at.mtile, at.lane, 32 * NSPLIT};
  const auto fetch = [&](int c, int kk, int nn) {
    const int i = ((first_slot + c) % slots) * (WIDTH * WIDTH / 2) + (kk * 8 + nn) * 32 + at.lane;
    return BFragment{hi2[i], lo2[i]};
  };
  cluster.sync();
  for (int s = 0; s < steps; ++s) {
    if (rank == 0) {
      if (chain_warp) {
        step_chain<NSPLIT>(frag, exchange, h0, at, products, fetch, link);
      }
      __syncthreads();
      const float h = coupling * link;
      for (int i = threadIdx.x; i < quads; i += blockDim.x) {
        const uint4 a = shared_split[i], b = shared_split[quads + i];
        const float4 wq = make_float4(__uint_as_float(a.x) + __uint_as_float(b.x), __uint_as_float(a.y) + __uint_as_float(b.y),
                                      __uint_as_float(a.z) + __uint_as_float(b.z), __uint_as_float(a.w) + __uint_as_float(b.w));
        __stcg(g4 + i, synthetic_quad(wq, h));
      }
    }
    cluster.sync();
    const float c1 = correction(b1, s), c2 = correction(b2, s);
    const AdamArgs a{nullptr, nullptr, nullptr, nullptr, n, steps, lr, b1, b2, eps};
    for (int i = lo_q + threadIdx.x; i < hi_q; i += blockDim.x) {
      float4 wq = w4[i], mq = m4[i], vq = v4[i];
      adam_four(wq, mq, vq, __ldcg(g4 + i), c1, c2, a);
      w4[i] = wq;
      m4[i] = mq;
      v4[i] = vq;
      put_split(i, wq);
    }
    cluster.sync();
  }
  if (chain_warp && at.part == 0) store_fragments(frag, out, at.r0, at.t);
#endif
}

// ----------------------------------------------------------------------------------------------
// host

// The exact chain h_{c+1} = leaky(h_c W) in double, and an elementwise bound E on how far a kernel
// whose every product term carries a relative error of at most gamma (operand rounding and the
// accumulation's, as a forward-error bound |fl(sum a b) - sum a b| <= gamma sum |a||b|) can lie
// from it. To first order, with leaky 1-Lipschitz and its own rounding (u32 |h|):
//   E_{c+1} = E_c |W| + gamma (|h_c| + E_c) |W| + u32 |h_{c+1}|,  E_0 = 0 (h_0 is float32).
struct Reference {
  std::vector<double> h, bound;
};

// Product c uses ws[c % ws.size()] (each [WIDTH, WIDTH], row-major [k][o]).
static Reference reference_chain(const std::vector<float>& h0, const std::vector<std::vector<float>>& ws, int chain,
                                 double gamma) {
  const double u32 = std::ldexp(1.0, -24);
  std::vector<double> h(h0.begin(), h0.end()), e(h.size(), 0.0), next(h.size()), next_e(h.size());
  for (int c = 0; c < chain; ++c) {
    const std::vector<float>& w = ws[c % ws.size()];
    for (int r = 0; r < ROWS; ++r)
      for (int o = 0; o < WIDTH; ++o) {
        double s = 0.0, abs_s = 0.0, err = 0.0;
        for (int k = 0; k < WIDTH; ++k) {
          const double wk = double(w[k * WIDTH + o]);
          s += h[r * WIDTH + k] * wk;
          abs_s += std::fabs(h[r * WIDTH + k]) * std::fabs(wk);
          err += e[r * WIDTH + k] * std::fabs(wk);
        }
        next[r * WIDTH + o] = s > 0 ? s : SLOPE * s;
        next_e[r * WIDTH + o] = err + gamma * (abs_s + err) + u32 * std::fabs(next[r * WIDTH + o]);
      }
    h.swap(next);
    e.swap(next_e);
  }
  return {h, e};
}

// max |a - ref| / max |ref|, and max over entries of |a - ref| / bound
// max(a, b), NaN if either is NaN (std::max(a, NaN) is a: a maximum would hide a NaN entry)
static double max_or_nan(double a, double b) { return (std::isnan(a) || std::isnan(b)) ? NAN : std::max(a, b); }

// bound_scale (optional): max bound / max |ref|, how large an error the bound lets pass
static void chain_errors(const std::vector<float>& a, const Reference& ref, double* rel, double* over_bound,
                         double* bound_scale = nullptr) {
  double err = 0.0, scale = 0.0, ratio = 0.0, largest_bound = 0.0;
  for (size_t i = 0; i < ref.h.size(); ++i) {
    const double d = std::fabs(double(a[i]) - ref.h[i]);
    err = max_or_nan(err, d);
    ratio = max_or_nan(ratio, ref.bound[i] > 0 ? d / ref.bound[i] : (d > 0 ? INFINITY : 0.0));
    scale = std::max(scale, std::fabs(ref.h[i]));
    largest_bound = std::max(largest_bound, ref.bound[i]);
  }
  *rel = err / scale;
  *over_bound = ratio;
  if (bound_scale) *bound_scale = largest_bound / scale;
}

// gamma of each precision (above), K = WIDTH terms, u = 2^-24 (float32), t = 2^-11 (TF32, round to
// nearest): "ieee" K u (float32 FMAs); "tf32" 2t + t^2 per operand pair and K additions of the
// accumulator at 2u each (the tensor cores' accumulation is not specified to round to nearest);
// "tf32x3" the dropped lo*lo term and the lo parts' own rounding, 3 t^2 (1 + t)^2, and 3K additions.
static double product_gamma(const char* precision) {
  const double u = std::ldexp(1.0, -24), t = std::ldexp(1.0, -11), K = WIDTH;
  if (std::strcmp(precision, "ieee") == 0) return K * u / (1 - K * u);
  if (std::strcmp(precision, "tf32") == 0) return 2 * t + t * t + K * 2 * u;
  return 3 * t * t * (1 + t) * (1 + t) + 3 * K * 2 * u;
}

// `steps` Adam steps from w0 with synthetic_gradient, in double with the kernels' float32 constants.
// m_out, v_out (optional): the moments after the last step.
static std::vector<double> adam_reference(const std::vector<float>& w0, int steps, double lr, double b1, double b2,
                                          double eps, std::vector<double>* m_out = nullptr,
                                          std::vector<double>* v_out = nullptr) {
  std::vector<double> w(w0.begin(), w0.end()), m(w0.size(), 0.0), v(w0.size(), 0.0);
  for (int s = 0; s < steps; ++s)
    for (size_t i = 0; i < w.size(); ++i) {
      const double g = double(1e-3f) * std::fabs(w[i]) + double(1e-4f);
      m[i] = b1 * m[i] + (1 - b1) * g;
      v[i] = b2 * v[i] + (1 - b2) * g * g;
      w[i] -= lr * (m[i] / (1 - std::pow(b1, s + 1))) / (std::sqrt(v[i] / (1 - std::pow(b2, s + 1))) + eps);
    }
  if (m_out) *m_out = m;
  if (v_out) *v_out = v;
  return w;
}

typedef void (*ChainKernel)(const float*, const float*, float*, int, int);

struct ChainVariant {
  const char* kernel;
  const char* precision;
  int nsplit;
  int accumulators;
  int threads;
  ChainKernel fn;
  int cluster = 1;  // blocks in the launch's one cluster (1: a plain launch of one block)
  int concurrent = 1;  // independent chains at once in the block (chains_mma), each writing its output
};

// The most chains chains_mma runs at once (its variants below), and its exchange buffers in
// dynamic shared memory: [concurrent][2][2][8][32] float4.
constexpr int MAX_CONCURRENT = 4;
static size_t chains_smem(int concurrent) {
  return concurrent > 1 ? size_t(concurrent) * 2 * 2 * 8 * 32 * sizeof(float4) : 0;
}

// Dynamic shared memory that every cluster launch asks for and leaves unused: with it no two blocks
// fit one multiprocessor (its 228 KiB), so a cluster's blocks run on multiprocessors of their own
// (cluster_sm, checked by the host). Each cluster kernel is allowed it once, before its first launch
// (allow_cluster_pad), not in the timed launches.
constexpr int CLUSTER_PAD_BYTES = 120 * 1024;

// The launch of one cluster of `cluster` blocks of `threads` threads (attr: its attribute's storage).
static cudaLaunchConfig_t one_cluster(int cluster, int threads, cudaLaunchAttribute* attr) {
  cudaLaunchConfig_t cfg = {};
  cfg.gridDim = dim3(cluster);
  cfg.blockDim = dim3(threads);
  cfg.dynamicSmemBytes = CLUSTER_PAD_BYTES;
  attr->id = cudaLaunchAttributeClusterDimension;
  attr->val.clusterDim.x = cluster;
  attr->val.clusterDim.y = 1;
  attr->val.clusterDim.z = 1;
  cfg.attrs = attr;
  cfg.numAttrs = 1;
  return cfg;
}

static void allow_cluster_pad(const void* fn) {
  CHECK(cudaFuncSetAttribute(fn, cudaFuncAttributeMaxDynamicSharedMemorySize, CLUSTER_PAD_BYTES));
}

// How many distinct multiprocessors the blocks of the last cluster launch of `cluster` blocks ran on.
static int distinct_sms(int cluster) {
  int sm[8];
  CHECK(cudaMemcpyFromSymbol(sm, cluster_sm, sizeof sm));
  std::sort(sm, sm + cluster);
  return int(std::unique(sm, sm + cluster) - sm);
}

// One launch of a chain kernel: one block, or one cluster of v.cluster blocks.
static void launch_chain(const ChainVariant& v, const float* h0, const float* w, float* out, int steps, int chain) {
  if (v.cluster == 1) {
    v.fn<<<1, v.threads, chains_smem(v.concurrent)>>>(h0, w, out, steps, chain);
    return;
  }
  cudaLaunchAttribute attr;
  const cudaLaunchConfig_t cfg = one_cluster(v.cluster, v.threads, &attr);
  CHECK(cudaLaunchKernelEx(&cfg, v.fn, h0, w, out, steps, chain));
}

// One launch of cluster_adam<cluster> (2, 4 or 8 blocks).
static void launch_cluster_adam(int cluster, int threads, AdamArgs a, int mode) {
  cudaLaunchAttribute attr;
  const cudaLaunchConfig_t cfg = one_cluster(cluster, threads, &attr);
  void (*fn)(AdamArgs, int) = cluster == 2 ? cluster_adam<2> : cluster == 4 ? cluster_adam<4> : cluster_adam<8>;
  CHECK(cudaLaunchKernelEx(&cfg, fn, a, mode));
}

static float time_launches(const std::function<void()>& launch, int repeats) {
  cudaEvent_t start, stop;
  CHECK(cudaEventCreate(&start));
  CHECK(cudaEventCreate(&stop));
  launch();  // warm-up
  CHECK(cudaDeviceSynchronize());
  float best = 1e30f;
  for (int r = 0; r < repeats; ++r) {
    CHECK(cudaEventRecord(start));
    launch();
    CHECK(cudaEventRecord(stop));
    CHECK(cudaEventSynchronize(stop));
    float ms;
    CHECK(cudaEventElapsedTime(&ms, start, stop));
    best = std::min(best, ms);
  }
  CHECK(cudaEventDestroy(start));
  CHECK(cudaEventDestroy(stop));
  return best;
}

static std::vector<int> parse_list(const char* s) {
  std::vector<int> out;
  std::string str(s);
  size_t pos = 0;
  while (pos < str.size()) {
    size_t end = str.find(',', pos);
    if (end == std::string::npos) end = str.size();
    if (end > pos) out.push_back(std::atoi(str.substr(pos, end - pos).c_str()));
    pos = end + 1;
  }
  return out;
}


// ----------------------------------------------------------------------------------------------
// seed_steps, grid_step, cluster_step: each seed's data drawn apart; checks against the host for
// every seed the kernel runs, then timings.
typedef void (*SeedKernel)(const float*, const float*, float*, float*, float*, float*, float*, int, int, int, int,
                           float, float, float, float, float);

// Slot `slot` of one seed's weights `src` as a [k][o] matrix (the B-fragment order undone).
static std::vector<float> slot_matrix(const float* src, int slot) {
  std::vector<float> W(WIDTH * WIDTH);
  src += size_t(slot) * WIDTH * WIDTH;
  for (int kk = 0; kk < 8; ++kk)
    for (int nn = 0; nn < 8; ++nn)
      for (int lane = 0; lane < 32; ++lane)
        for (int j = 0; j < 2; ++j)
          W[(8 * kk + 2 * (lane % 4) + j) * WIDTH + 8 * nn + lane / 4] = src[((kk * 8 + nn) * 32 + lane) * 2 + j];
  return W;
}

// A whole-step kernel: seed_steps (cluster 0: one block per seed), grid_step (cluster -1: one seed
// over a cooperative grid of one block per multiprocessor) or cluster_step / cluster_step_presplit
// (cluster >= 2: one seed over a cluster of that many blocks).
struct SeedVariant {
  const char* kernel;
  int nsplit, threads, cluster;
  SeedKernel fn;
};

struct SeedArgs {
  const float* h0;
  const float* w0;
  float *w_out, *m, *v, *out, *g;
  int n, steps, products, first_slot;
  float coupling, lr, b1, b2, eps;
};

// Dynamic shared memory of a launch: the weights (seed_steps), block 0's weights (grid_step) or
// block 0's weights and gradient, or their TF32 parts (cluster_step, cluster_step_presplit); for
// one seed over many blocks at least the pad that keeps every block on a multiprocessor of its own.
static size_t seed_smem(const SeedVariant& sv, int n) {
  const size_t w = size_t(n) * sizeof(float);
  if (sv.cluster == 0) return w;
  return std::max(sv.cluster >= 2 ? 2 * w : w, size_t(CLUSTER_PAD_BYTES));
}

static void launch_seed_variant(const SeedVariant& sv, int seeds, int grid_blocks, SeedArgs a) {
  const size_t smem = seed_smem(sv, a.n);
  if (sv.cluster == 0) {
    sv.fn<<<seeds, sv.threads, smem>>>(a.h0, a.w0, a.w_out, a.m, a.v, a.out, a.g, a.n, a.steps, a.products,
                                       a.first_slot, a.coupling, a.lr, a.b1, a.b2, a.eps);
    return;
  }
  if (sv.cluster < 0) {
    void* args[] = {&a.h0, &a.w0,    &a.w_out,      &a.m,        &a.v,  &a.out, &a.g,  &a.n,
                    &a.steps, &a.products, &a.first_slot, &a.coupling, &a.lr, &a.b1,  &a.b2, &a.eps};
    CHECK(cudaLaunchCooperativeKernel((void*)sv.fn, grid_blocks, sv.threads, args, smem, 0));
    return;
  }
  cudaLaunchAttribute attr;
  cudaLaunchConfig_t cfg = one_cluster(sv.cluster, sv.threads, &attr);
  cfg.dynamicSmemBytes = smem;
  CHECK(cudaLaunchKernelEx(&cfg, sv.fn, a.h0, a.w0, a.w_out, a.m, a.v, a.out, a.g, a.n, a.steps, a.products,
                           a.first_slot, a.coupling, a.lr, a.b1, a.b2, a.eps));
}

// The variant's place in the JSON lines: its cluster size, and for a cluster how many
// multiprocessors the last launch's blocks ran on.
static std::string seed_variant_fields(const SeedVariant& sv, bool sms) {
  char buf[96];
  if (sv.cluster >= 2 && sms)
    snprintf(buf, sizeof buf, ", \"cluster\": %d, \"distinct_sms\": %d", sv.cluster, distinct_sms(sv.cluster));
  else if (sv.cluster >= 2)
    snprintf(buf, sizeof buf, ", \"cluster\": %d", sv.cluster);
  else
    buf[0] = 0;
  return buf;
}

static int seed_benchmark(const std::vector<int>& seed_counts, int n, int loop, int products, int repeats,
                          std::mt19937& rng) {
  const int max_seeds = *std::max_element(seed_counts.begin(), seed_counts.end());
  // Checked chains stay short: the chain's forward-error bound grows about eightfold per product
  // (|W|'s row sums), so beyond four products a wrong weight would pass it. One step's four products
  // on slots 0..3, then two steps of two products from the last slot, wrapping to slot 0, the second
  // step on the weights the first step's Adam left: every slot, the wrap and the update are checked.
  const int slots = n / (WIDTH * WIDTH), check_steps = 5;
  const float lr = 1e-3f, b1 = 0.9f, b2 = 0.999f, eps = 1e-8f;
  cudaDeviceProp prop;
  CHECK(cudaGetDeviceProperties(&prop, 0));
  const bool clusters = prop.major >= 9;
  std::normal_distribution<float> normal(0.f, 1.f);
  const float scale = std::sqrt(2.f / (1.f + SLOPE * SLOPE) / WIDTH);
  std::vector<float> hs(size_t(max_seeds) * ROWS * WIDTH), ws(size_t(max_seeds) * n);
  for (auto& x : hs) x = normal(rng);
  for (auto& x : ws) x = scale * normal(rng);
  float *d_h, *d_w, *d_wout, *d_m, *d_v, *d_out, *d_g;
  CHECK(cudaMalloc(&d_h, hs.size() * sizeof(float)));
  CHECK(cudaMalloc(&d_w, ws.size() * sizeof(float)));
  CHECK(cudaMalloc(&d_wout, ws.size() * sizeof(float)));
  CHECK(cudaMalloc(&d_m, ws.size() * sizeof(float)));
  CHECK(cudaMalloc(&d_v, ws.size() * sizeof(float)));
  CHECK(cudaMalloc(&d_out, hs.size() * sizeof(float)));
  CHECK(cudaMalloc(&d_g, size_t(n) * sizeof(float)));
  CHECK(cudaMemcpy(d_h, hs.data(), hs.size() * sizeof(float), cudaMemcpyHostToDevice));
  CHECK(cudaMemcpy(d_w, ws.data(), ws.size() * sizeof(float), cudaMemcpyHostToDevice));
  auto zero_moments = [&] {
    CHECK(cudaMemset(d_m, 0, ws.size() * sizeof(float)));
    CHECK(cudaMemset(d_v, 0, ws.size() * sizeof(float)));
  };

  // Adam with synthetic_gradient (coupling 0) for every seed, in double; the moments too, which
  // follow the gradient itself (the update divides its size out, so a wrong gradient hands off
  // shows in m and v at full size and in w only as its drift)
  std::vector<double> mr, vr;
  const std::vector<double> wr = adam_reference(ws, check_steps, lr, b1, b2, eps, &mr, &vr);

  const SeedVariant variants[] = {{"seed_steps", 1, 128, 0, seed_steps<1, 128>},
                                  {"seed_steps", 1, 256, 0, seed_steps<1, 256>},
                                  {"seed_steps", 2, 128, 0, seed_steps<2, 128>},
                                  {"seed_steps", 2, 256, 0, seed_steps<2, 256>},
                                  {"grid_step", 2, 256, -1, grid_step<2, 256>},
                                  {"grid_step", 2, 512, -1, grid_step<2, 512>},
                                  {"cluster_step", 2, 256, 2, cluster_step<2, 2, 256>},
                                  {"cluster_step", 2, 512, 2, cluster_step<2, 2, 512>},
                                  {"cluster_step", 2, 256, 4, cluster_step<4, 2, 256>},
                                  {"cluster_step", 2, 512, 4, cluster_step<4, 2, 512>},
                                  {"cluster_step", 2, 256, 8, cluster_step<8, 2, 256>},
                                  {"cluster_step", 2, 512, 8, cluster_step<8, 2, 512>},
                                  {"cluster_step_presplit", 2, 256, 2, cluster_step_presplit<2, 2, 256>},
                                  {"cluster_step_presplit", 2, 512, 2, cluster_step_presplit<2, 2, 512>},
                                  {"cluster_step_presplit", 2, 256, 4, cluster_step_presplit<4, 2, 256>},
                                  {"cluster_step_presplit", 2, 512, 4, cluster_step_presplit<4, 2, 512>},
                                  {"cluster_step_presplit", 2, 256, 8, cluster_step_presplit<8, 2, 256>},
                                  {"cluster_step_presplit", 2, 512, 8, cluster_step_presplit<8, 2, 512>}};
  const double gamma = product_gamma("tf32x3");
  std::vector<float> got_out(hs.size()), got_w(ws.size()), w1(ws.size()), got_m(ws.size()), got_v(ws.size());
  for (const SeedVariant& sv : variants) {
    if (sv.cluster >= 2 && !clusters) continue;
    const int threads = sv.threads, grid_blocks = prop.multiProcessorCount;
    // one seed over many multiprocessors (grid_step, cluster_step), or one block per seed
    const int check_seeds = sv.cluster == 0 ? max_seeds : 1;
    const size_t smem = seed_smem(sv, n);
    cudaFuncAttributes attr;
    CHECK(cudaFuncGetAttributes(&attr, sv.fn));
    if (smem + attr.sharedSizeBytes > prop.sharedMemPerBlockOptin) {
      // this variant's weights do not fit a block's shared memory: said in a line, the others still run
      printf("{\"skipped\": \"%s\", \"nsplit\": %d, \"threads\": %d, \"n\": %d, \"reason\": \"%zu bytes of "
             "weights and the kernel's own %zu exceed a thread block's %zu bytes of shared memory\"%s}\n",
             sv.kernel, sv.nsplit, threads, n, smem, size_t(attr.sharedSizeBytes), size_t(prop.sharedMemPerBlockOptin),
             seed_variant_fields(sv, false).c_str());
      continue;
    }
    CHECK(cudaFuncSetAttribute(sv.fn, cudaFuncAttributeMaxDynamicSharedMemorySize, int(smem)));
    int blocks_per_sm = 0;
    CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&blocks_per_sm, sv.fn, threads, smem));
    if (blocks_per_sm < 1) {
      fprintf(stderr, "%s: one block of %d threads with %zu bytes of weights does not fit a multiprocessor\n",
              sv.kernel, threads, smem);
      return 1;
    }
    SeedArgs args{d_h, d_w, d_wout, d_m, d_v, d_out, d_g, n, 0, 0, 0, 0.f, lr, b1, b2, eps};
    struct ChainCheck {
      int steps, products, first_slot;
    };
    for (const ChainCheck cc : {ChainCheck{1, std::min(4, slots), 0}, ChainCheck{2, 2, slots - 1}}) {
      zero_moments();
      args.steps = cc.steps, args.products = cc.products, args.first_slot = cc.first_slot, args.coupling = 0.f;
      launch_seed_variant(sv, check_seeds, grid_blocks, args);
      CHECK(cudaGetLastError());
      CHECK(cudaMemcpy(got_out.data(), d_out, got_out.size() * sizeof(float), cudaMemcpyDeviceToHost));
      if (cc.steps == 1)  // the weights after one step (with coupling 0 Adam does not see the products)
        CHECK(cudaMemcpy(w1.data(), d_wout, w1.size() * sizeof(float), cudaMemcpyDeviceToHost));
      double worst_rel = 0.0, worst_over = 0.0, widest_bound = 0.0;
      for (int i = 0; i < check_seeds; ++i) {
        // the last step's chain: from the input rows, on the weights that step started with
        const float* wsrc = (cc.steps == 1 ? ws.data() : w1.data()) + size_t(i) * n;
        std::vector<std::vector<float>> wi;
        for (int c = 0; c < cc.products; ++c) wi.push_back(slot_matrix(wsrc, (cc.first_slot + c) % slots));
        std::vector<float> hi(ROWS * WIDTH), gi(ROWS * WIDTH);
        std::copy_n(hs.data() + size_t(i) * ROWS * WIDTH, ROWS * WIDTH, hi.data());
        std::copy_n(got_out.data() + size_t(i) * ROWS * WIDTH, ROWS * WIDTH, gi.data());
        double rel, over, bound_scale;
        chain_errors(gi, reference_chain(hi, wi, cc.products, gamma), &rel, &over, &bound_scale);
        worst_rel = max_or_nan(worst_rel, rel);
        worst_over = max_or_nan(worst_over, over);
        widest_bound = std::max(widest_bound, bound_scale);
      }
      printf("{\"check\": \"chain_%s\", \"precision\": \"tf32x3\", \"nsplit\": %d, \"accumulators\": 3, "
             "\"threads\": %d, \"seeds\": %d, \"steps\": %d, \"products\": %d, \"first_slot\": %d, "
             "\"max_rel_err\": %.3e, \"max_err_over_bound\": %.3e, \"max_bound_over_max_h\": %.3e%s}\n",
             sv.kernel, sv.nsplit, threads, check_seeds, cc.steps, cc.products, cc.first_slot, worst_rel, worst_over,
             widest_bound, seed_variant_fields(sv, true).c_str());
    }
    // Adam over several steps, every seed: its error relative to its own update
    zero_moments();
    args.steps = check_steps, args.products = 2, args.first_slot = 0, args.coupling = 0.f;
    launch_seed_variant(sv, check_seeds, grid_blocks, args);
    CHECK(cudaGetLastError());
    CHECK(cudaMemcpy(got_w.data(), d_wout, got_w.size() * sizeof(float), cudaMemcpyDeviceToHost));
    CHECK(cudaMemcpy(got_m.data(), d_m, got_m.size() * sizeof(float), cudaMemcpyDeviceToHost));
    CHECK(cudaMemcpy(got_v.data(), d_v, got_v.size() * sizeof(float), cudaMemcpyDeviceToHost));
    std::string errs, abs_ws, updates, m_errs, v_errs;
    for (int i = 0; i < check_seeds; ++i) {
      double err = 0.0, max_abs_w = 0.0, max_update = 0.0, m_err = 0.0, m_max = 0.0, v_err = 0.0, v_max = 0.0;
      for (size_t k = size_t(i) * n; k < size_t(i + 1) * n; ++k) {
        err = max_or_nan(err, std::fabs(double(got_w[k]) - wr[k]));
        max_abs_w = std::max(max_abs_w, std::fabs(wr[k]));
        max_update = std::max(max_update, std::fabs(wr[k] - double(ws[k])));
        m_err = max_or_nan(m_err, std::fabs(double(got_m[k]) - mr[k]));
        m_max = std::max(m_max, std::fabs(mr[k]));
        v_err = max_or_nan(v_err, std::fabs(double(got_v[k]) - vr[k]));
        v_max = std::max(v_max, std::fabs(vr[k]));
      }
      char buf[64];
      snprintf(buf, sizeof buf, "%s%.3e", i ? ", " : "", err / max_update);
      errs += buf;
      snprintf(buf, sizeof buf, "%s%.6e", i ? ", " : "", max_abs_w);
      abs_ws += buf;
      snprintf(buf, sizeof buf, "%s%.6e", i ? ", " : "", max_update);
      updates += buf;
      snprintf(buf, sizeof buf, "%s%.3e", i ? ", " : "", m_err / m_max);
      m_errs += buf;
      snprintf(buf, sizeof buf, "%s%.3e", i ? ", " : "", v_err / v_max);
      v_errs += buf;
    }
    printf("{\"check\": \"adam_%s\", \"nsplit\": %d, \"threads\": %d, \"seeds\": %d, \"steps\": %d, "
           "\"max_err_over_update\": [%s], \"max_abs_w\": [%s], \"max_update\": [%s], "
           "\"m_max_rel_err\": [%s], \"v_max_rel_err\": [%s]%s}\n",
           sv.kernel, sv.nsplit, threads, check_seeds, check_steps, errs.c_str(), abs_ws.c_str(), updates.c_str(),
           m_errs.c_str(), v_errs.c_str(), seed_variant_fields(sv, true).c_str());
    // timings; each line says whether the timed chains' last outputs are finite (values do not change
    // the tensor cores' speed, but a NaN is reported rather than hidden)
    const std::vector<int> timed_seeds = sv.cluster == 0 ? seed_counts : std::vector<int>{1};
    for (int seeds : timed_seeds)
      for (int p : {0, products}) {
        zero_moments();
        args.steps = loop, args.products = p, args.first_slot = 0, args.coupling = 1e-9f;
        const float ms = time_launches([&] { launch_seed_variant(sv, seeds, grid_blocks, args); }, repeats);
        CHECK(cudaGetLastError());
        CHECK(cudaMemcpy(got_out.data(), d_out, size_t(seeds) * ROWS * WIDTH * sizeof(float), cudaMemcpyDeviceToHost));
        bool finite = true;
        double max_abs = 0.0;
        for (size_t k = 0; k < size_t(seeds) * ROWS * WIDTH; ++k) {
          finite = finite && std::isfinite(got_out[k]);
          max_abs = std::max(max_abs, std::fabs(double(got_out[k])));
        }
        printf("{\"kernel\": \"%s\", \"precision\": \"tf32x3\", \"nsplit\": %d, \"threads\": %d, "
               "\"blocks_per_sm\": %d, \"blocks\": %d, \"seeds\": %d, \"products\": %d, \"n\": %d, \"steps\": %d, "
               "\"us_per_step\": %.4f, \"out_finite\": %s, \"out_max_abs\": %.3e%s}\n",
               sv.kernel, sv.nsplit, threads, blocks_per_sm,
               sv.cluster == 0 ? seeds : sv.cluster < 0 ? grid_blocks : sv.cluster, seeds, p, n, loop,
               1e3 * ms / loop, finite ? "true" : "false", max_abs, seed_variant_fields(sv, false).c_str());
      }
  }
  return 0;
}

int main(int argc, char** argv) {
  // arguments: chains steps repeats adam_n adam_steps seed_counts seed_n seed_loop seed_products
  const std::vector<int> chains = parse_list(argc > 1 ? argv[1] : "1,8,32");
  const int steps = argc > 2 ? std::atoi(argv[2]) : 2000;
  const int repeats = argc > 3 ? std::atoi(argv[3]) : 5;
  const int adam_n = argc > 4 ? std::atoi(argv[4]) : 41600;
  const int adam_steps = argc > 5 ? std::atoi(argv[5]) : 2000;
  const std::vector<int> seed_counts = parse_list(argc > 6 ? argv[6] : "1,132,256");
  const int seed_n = argc > 7 ? std::atoi(argv[7]) : 22664;
  const int seed_loop = argc > 8 ? std::atoi(argv[8]) : 500;
  const int seed_products = argc > 9 ? std::atoi(argv[9]) : 32;
  if (adam_n % 4 != 0 || seed_n % 4 != 0) {
    fprintf(stderr, "adam_n=%d, seed_n=%d: the Adam kernels take entries in fours; give multiples of 4\n", adam_n,
            seed_n);
    return 2;
  }
  if (seed_n < WIDTH * WIDTH || seed_counts.empty()) {
    fprintf(stderr, "seed_n=%d: the seeds' kernel needs at least one %d x %d weight slot, and a seed count\n",
            seed_n, WIDTH, WIDTH);
    return 2;
  }

  cudaDeviceProp prop;
  CHECK(cudaGetDeviceProperties(&prop, 0));
  printf("{\"device\": \"%s\", \"multiprocessors\": %d, \"sm\": \"%d.%d\"}\n", prop.name, prop.multiProcessorCount,
         prop.major, prop.minor);

  std::mt19937 rng(0);
  std::normal_distribution<float> normal(0.f, 1.f);
  std::vector<float> h0(ROWS * WIDTH), w(WIDTH * WIDTH);
  for (auto& x : h0) x = normal(rng);
  // He's scale for leaky ReLU keeps the activations' size along the chain
  const float scale = std::sqrt(2.f / (1.f + SLOPE * SLOPE) / WIDTH);
  for (auto& x : w) x = scale * normal(rng);
  float *d_h0, *d_w, *d_out;
  CHECK(cudaMalloc(&d_h0, h0.size() * sizeof(float)));
  CHECK(cudaMalloc(&d_w, w.size() * sizeof(float)));
  CHECK(cudaMalloc(&d_out, MAX_CONCURRENT * h0.size() * sizeof(float)));
  CHECK(cudaMemcpy(d_h0, h0.data(), h0.size() * sizeof(float), cudaMemcpyHostToDevice));
  CHECK(cudaMemcpy(d_w, w.data(), w.size() * sizeof(float), cudaMemcpyHostToDevice));

  const ChainVariant variants[] = {
      {"chain_fma", "ieee", 0, 1, 256, chain_fma},
      {"chain_mma", "tf32", 1, 1, 64, chain_mma<1, 1, 1>},
      {"chain_mma", "tf32x3", 1, 1, 64, chain_mma<3, 1, 1>},
      {"chain_mma", "tf32x3", 1, 3, 64, chain_mma<3, 1, 3>},
      {"chain_mma", "tf32x3", 2, 1, 128, chain_mma<3, 2, 1>},
      {"chain_mma", "tf32x3", 2, 3, 128, chain_mma<3, 2, 3>},
      {"chain_mma", "tf32x3", 4, 1, 256, chain_mma<3, 4, 1>},
      {"chains_mma", "tf32x3", 2, 3, 256, chains_mma<2, 2>, 1, 2},
      {"chains_mma", "tf32x3", 2, 3, 384, chains_mma<2, 3>, 1, 3},
      {"chains_mma", "tf32x3", 2, 3, 512, chains_mma<2, MAX_CONCURRENT>, 1, MAX_CONCURRENT},
      {"chain_cluster", "tf32x3", 1, 3, 64, chain_cluster<2, 1>, 2},
      {"chain_cluster", "tf32x3", 2, 3, 128, chain_cluster<2, 2>, 2},
      {"chain_cluster", "tf32x3", 1, 3, 64, chain_cluster<4, 1>, 4},
      {"chain_cluster", "tf32x3", 2, 3, 128, chain_cluster<4, 2>, 4},
      {"chain_cluster", "tf32x3", 1, 3, 64, chain_cluster<8, 1>, 8},
#ifdef KERNEL_CUDA_WGMMA
      {"chain_wgmma", "tf32", 0, 1, 128, chain_wgmma<1, 1>},
      {"chain_wgmma", "tf32x3", 0, 1, 128, chain_wgmma<3, 1>},
      {"chain_wgmma", "tf32x3", 0, 3, 128, chain_wgmma<3, 3>},
#endif
  };
  const int check_chain = 4;
  const std::vector<std::vector<float>> one_weight{w};
  std::vector<float> got(MAX_CONCURRENT * h0.size());
  const bool clusters = prop.major >= 9;  // thread-block clusters need sm_90
  for (const ChainVariant& v : variants) {
    if (v.cluster > 1 && !clusters) continue;
    if (v.cluster > 1) allow_cluster_pad((const void*)v.fn);
    if (v.concurrent > 1)
      CHECK(cudaFuncSetAttribute((const void*)v.fn, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                 int(chains_smem(v.concurrent))));
    const Reference ref = reference_chain(h0, one_weight, check_chain, product_gamma(v.precision));
    CHECK(cudaMemset(d_out, 0, v.concurrent * h0.size() * sizeof(float)));
    launch_chain(v, d_h0, d_w, d_out, 1, check_chain);
    CHECK(cudaGetLastError());
    CHECK(cudaMemcpy(got.data(), d_out, v.concurrent * h0.size() * sizeof(float), cudaMemcpyDeviceToHost));
    double rel = 0.0, over_bound = 0.0;  // the worst of the chains
    for (int c = 0; c < v.concurrent; ++c) {
      const std::vector<float> one(got.begin() + c * h0.size(), got.begin() + (c + 1) * h0.size());
      double rel_c, over_c;
      chain_errors(one, ref, &rel_c, &over_c);
      rel = max_or_nan(rel, rel_c);
      over_bound = max_or_nan(over_bound, over_c);
    }
    printf("{\"check\": \"%s\", \"precision\": \"%s\", \"nsplit\": %d, \"accumulators\": %d, \"cluster\": %d, "
           "\"distinct_sms\": %d, \"concurrent\": %d, \"products\": %d, \"max_rel_err\": %.3e, "
           "\"max_err_over_bound\": %.3e}\n",
           v.kernel, v.precision, v.nsplit, v.accumulators, v.cluster, v.cluster > 1 ? distinct_sms(v.cluster) : 1,
           v.concurrent, check_chain, rel, over_bound);
    for (int chain : chains) {
      const float ms = time_launches([&] { launch_chain(v, d_h0, d_w, d_out, steps, chain); }, repeats);
      CHECK(cudaGetLastError());
      printf("{\"kernel\": \"%s\", \"precision\": \"%s\", \"nsplit\": %d, \"accumulators\": %d, \"threads\": %d, "
             "\"cluster\": %d, \"concurrent\": %d, \"chain\": %d, \"steps\": %d, \"us_per_iteration\": %.4f}\n",
             v.kernel, v.precision, v.nsplit, v.accumulators, v.threads, v.cluster, v.concurrent, chain, steps,
             1e3 * ms / steps);
    }
  }

  // Adam: host reference of a few steps, then the timings
  std::vector<float> w0(adam_n);
  for (auto& x : w0) x = 0.1f * normal(rng);
  AdamArgs a{nullptr, nullptr, nullptr, nullptr, adam_n, 0, 1e-3f, 0.9f, 0.999f, 1e-8f};
  CHECK(cudaMalloc(&a.w, adam_n * sizeof(float)));
  CHECK(cudaMalloc(&a.m, adam_n * sizeof(float)));
  CHECK(cudaMalloc(&a.v, adam_n * sizeof(float)));
  CHECK(cudaMalloc(&a.g, adam_n * sizeof(float)));
  auto reset = [&] {
    CHECK(cudaMemcpy(a.w, w0.data(), adam_n * sizeof(float), cudaMemcpyHostToDevice));
    CHECK(cudaMemset(a.m, 0, adam_n * sizeof(float)));
    CHECK(cudaMemset(a.v, 0, adam_n * sizeof(float)));
  };
  const int check_steps = 5;
  const std::vector<double> wr = adam_reference(w0, check_steps, a.lr, a.b1, a.b2, a.eps);
  // relative to the size of the update, the quantity the kernel computes
  double max_abs_w = 0.0, max_update = 0.0;
  for (int i = 0; i < adam_n; ++i) {
    max_abs_w = std::max(max_abs_w, std::fabs(wr[i]));
    max_update = std::max(max_update, std::fabs(wr[i] - double(w0[i])));
  }
  auto update_error = [&](const std::vector<float>& got_w) {
    double err = 0.0;
    for (int i = 0; i < adam_n; ++i) {
      err = max_or_nan(err, std::fabs(double(got_w[i]) - wr[i]));
    }
    return err / max_update;
  };
  int blocks_per_sm = 0;
  int threads = 1024;
  CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&blocks_per_sm, grid_adam, threads, 0));
  const int grid = prop.multiProcessorCount;
  if (blocks_per_sm < 1) {
    fprintf(stderr, "grid_adam cannot run one block of %d threads per multiprocessor\n", threads);
    return 1;
  }
  auto launch_grid = [&](int mode, int n_steps) {
    a.steps = n_steps;
    void* args[] = {&a, &mode};
    CHECK(cudaLaunchCooperativeKernel((void*)grid_adam, grid, threads, args, 0, 0));
  };
  std::vector<float> got_w(adam_n);
  for (int bt : {256, 1024}) {
    for (const char* kernel : {"grid_adam", "block_adam"}) {
      reset();
      if (kernel[0] == 'g') {
        threads = bt;
        launch_grid(1, check_steps);
      } else {
        a.steps = check_steps;
        block_adam<<<1, bt>>>(a);
        CHECK(cudaGetLastError());
      }
      CHECK(cudaMemcpy(got_w.data(), a.w, adam_n * sizeof(float), cudaMemcpyDeviceToHost));
      printf("{\"check\": \"%s\", \"threads\": %d, \"steps\": %d, \"max_err_over_update\": %.3e, "
             "\"max_abs_w\": %.6e, \"max_update\": %.6e}\n",
             kernel, bt, check_steps, update_error(got_w), max_abs_w, max_update);
    }
  }

  for (int mode = 0; mode < 2; ++mode) {
    for (int bt : {256, 1024}) {
      threads = bt;
      reset();
      const float ms = time_launches([&] { launch_grid(mode, adam_steps); }, repeats);
      printf("{\"kernel\": \"grid_adam\", \"mode\": \"%s\", \"blocks\": %d, \"threads\": %d, \"n\": %d, "
             "\"steps\": %d, \"us_per_step\": %.4f}\n",
             mode == 0 ? "sync" : "update", grid, threads, adam_n, adam_steps, 1e3 * ms / adam_steps);
    }
  }
  for (int bt : {256, 1024}) {
    reset();
    const float ms = time_launches([&] { a.steps = adam_steps; block_adam<<<1, bt>>>(a); }, repeats);
    CHECK(cudaGetLastError());
    printf("{\"kernel\": \"block_adam\", \"mode\": \"block\", \"blocks\": 1, \"threads\": %d, \"n\": %d, \"steps\": %d, "
           "\"us_per_step\": %.4f}\n",
           bt, adam_n, adam_steps, 1e3 * ms / adam_steps);
  }
  if (clusters)
    for (const void* fn : {(const void*)cluster_adam<2>, (const void*)cluster_adam<4>, (const void*)cluster_adam<8>})
      allow_cluster_pad(fn);
  for (int cluster : {2, 4, 8}) {
    if (!clusters) break;
    for (int bt : {256, 1024}) {
      for (int mode = 1; mode < 3; ++mode) {
        reset();
        a.steps = check_steps;
        launch_cluster_adam(cluster, bt, a, mode);
        CHECK(cudaGetLastError());
        CHECK(cudaMemcpy(got_w.data(), a.w, adam_n * sizeof(float), cudaMemcpyDeviceToHost));
        printf("{\"check\": \"cluster_adam\", \"mode\": \"%s\", \"cluster\": %d, \"distinct_sms\": %d, "
               "\"threads\": %d, \"steps\": %d, \"max_err_over_update\": %.3e, \"max_abs_w\": %.6e, "
               "\"max_update\": %.6e}\n",
               mode == 1 ? "update" : "local", cluster, distinct_sms(cluster), bt, check_steps, update_error(got_w),
               max_abs_w, max_update);
      }
      for (int mode = 0; mode < 3; ++mode) {
        reset();
        a.steps = adam_steps;
        const float ms = time_launches([&] { launch_cluster_adam(cluster, bt, a, mode); }, repeats);
        CHECK(cudaGetLastError());
        printf("{\"kernel\": \"cluster_adam\", \"mode\": \"%s\", \"cluster\": %d, \"blocks\": %d, \"threads\": %d, "
               "\"n\": %d, \"steps\": %d, \"us_per_step\": %.4f}\n",
               mode == 0 ? "sync" : mode == 1 ? "update" : "local", cluster, cluster, bt, adam_n, adam_steps,
               1e3 * ms / adam_steps);
      }
    }
  }
  return seed_benchmark(seed_counts, seed_n, seed_loop, seed_products, repeats, rng);
}
