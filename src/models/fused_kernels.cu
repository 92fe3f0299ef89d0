// Fused CUDA kernels of the flow model's inference path (see fused_kernels.h for the contracts).
#include "models/fused_kernels.h"

#include <type_traits>

namespace simu::models::kernels {

namespace {

// The 16-bit storage types of the kernels: bf16 (training, bf16 autocast) and fp16 (the released
// inference precision). Pairs of values are read and written as one 4-byte word.
template <typename T>
struct Half2;
template <>
struct Half2<__nv_bfloat16> {
  using T2 = __nv_bfloat162;
  static __device__ __forceinline__ float2 to_float2(T2 v) { return __bfloat1622float2(v); }
  static __device__ __forceinline__ T2 pack(float a, float b) { return __floats2bfloat162_rn(a, b); }
};
template <>
struct Half2<__half> {
  using T2 = __half2;
  static __device__ __forceinline__ float2 to_float2(T2 v) { return __half22float2(v); }
  static __device__ __forceinline__ T2 pack(float a, float b) { return __floats2half2_rn(a, b); }
};

__device__ __forceinline__ float warp_sum(float v) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffffu, v, o);
  return v;
}

// Mean and 1/sqrt(variance + eps) of one row held in registers (lane's VPL float4; C = 128 * VPL) by
// one warp: the variance about the mean, two passes over registers (as torch's fp32 layer_norm).
template <int VPL>
__device__ __forceinline__ void row_mean_rstd(const float4 (&v)[VPL], float eps, float& mean, float& rstd) {
  constexpr int C = 128 * VPL;
  float s = 0.f;
#pragma unroll
  for (int i = 0; i < VPL; ++i) s += (v[i].x + v[i].y) + (v[i].z + v[i].w);
  mean = warp_sum(s) * (1.f / C);
  float q = 0.f;
#pragma unroll
  for (int i = 0; i < VPL; ++i) {
    const float a = v[i].x - mean, bb = v[i].y - mean, c = v[i].z - mean, d = v[i].w - mean;
    q += (a * a + bb * bb) + (c * c + d * d);
  }
  rstd = rsqrtf(warp_sum(q) * (1.f / C) + eps);
}

// The LayerNorm + affine of one row held in registers by one warp (row_mean_rstd), then
// y = (v - mean) * rstd * w + b stored as bf16.
template <typename T, int VPL>
__device__ __forceinline__ void layer_norm_affine_store(const float4 (&v)[VPL], int lane, int64_t row,
                                                        const float* __restrict__ w, const float* __restrict__ b,
                                                        T* __restrict__ y, int64_t rows_per_w, float eps) {
  constexpr int C = 128 * VPL;
  float mean, rstd;
  row_mean_rstd<VPL>(v, eps, mean, rstd);
  // Affine (per-row-group weight and bias), store bf16.
  const int64_t wr = row / rows_per_w;
  const float4* wv = reinterpret_cast<const float4*>(w + wr * C);
  const float4* bv = b ? reinterpret_cast<const float4*>(b + wr * C) : nullptr;
  typename Half2<T>::T2* yr = reinterpret_cast<typename Half2<T>::T2*>(y + row * C);
#pragma unroll
  for (int i = 0; i < VPL; ++i) {
    const int j = lane + 32 * i;
    const float4 ww = wv[j];
    const float4 bb = bv ? bv[j] : make_float4(0.f, 0.f, 0.f, 0.f);
    const float o0 = (v[i].x - mean) * rstd * ww.x + bb.x, o1 = (v[i].y - mean) * rstd * ww.y + bb.y;
    const float o2 = (v[i].z - mean) * rstd * ww.z + bb.z, o3 = (v[i].w - mean) * rstd * ww.w + bb.w;
    yr[2 * j] = Half2<T>::pack(o0, o1);
    yr[2 * j + 1] = Half2<T>::pack(o2, o3);
  }
}

// One warp per row; each lane keeps VPL float4 of the row in registers (C = 128 * VPL).
template <typename T, int VPL>
__global__ void layer_norm_affine_kernel(const float* __restrict__ x, const float* __restrict__ w,
                                              const float* __restrict__ b, T* __restrict__ y, int64_t rows,
                                              int64_t rows_per_w, float eps) {
  constexpr int C = 128 * VPL;
  const int lane = threadIdx.x & 31;
  const int64_t row = static_cast<int64_t>(blockIdx.x) * (blockDim.x / 32) + (threadIdx.x >> 5);
  if (row >= rows) return;
  const float4* xr = reinterpret_cast<const float4*>(x + row * C);
  float4 v[VPL];
#pragma unroll
  for (int i = 0; i < VPL; ++i) v[i] = xr[lane + 32 * i];
  layer_norm_affine_store<T, VPL>(v, lane, row, w, b, y, rows_per_w, eps);
}

// layer_norm_affine_kernel with the residual update in front: x_out = x + h * gate (fp32), then
// the LayerNorm + affine of x_out stored as bf16. One warp per row, VPL float4 per lane.
template <typename T, int VPL>
__global__ void residual_layer_norm_affine_kernel(const float* __restrict__ x, const T* __restrict__ h, int64_t h_rows,
                                                       const T* __restrict__ h_tail, const float* __restrict__ gate,
                                                       int64_t rows_per_gate,
                                                       float* __restrict__ x_out, const float* __restrict__ w,
                                                       const float* __restrict__ b, T* __restrict__ y,
                                                       int64_t rows, int64_t rows_per_w, float eps) {
  constexpr int C = 128 * VPL;
  const int lane = threadIdx.x & 31;
  const int64_t row = static_cast<int64_t>(blockIdx.x) * (blockDim.x / 32) + (threadIdx.x >> 5);
  if (row >= rows) return;
  const float4* xr = reinterpret_cast<const float4*>(x + row * C);
  // Rows past h's own read the broadcast tail row (CFG's zero-condition rows).
  const typename Half2<T>::T2* hr = reinterpret_cast<const typename Half2<T>::T2*>(row < h_rows ? h + row * C : h_tail);
  const float4* gr = gate ? reinterpret_cast<const float4*>(gate + (row / rows_per_gate) * C) : nullptr;
  float4* xo = reinterpret_cast<float4*>(x_out + row * C);
  // Residual update (x + h * gate, as addcmul computes it), written out.
  float4 v[VPL];
#pragma unroll
  for (int i = 0; i < VPL; ++i) {
    const int j = lane + 32 * i;
    const float4 a = xr[j];
    const float2 h01 = Half2<T>::to_float2(hr[2 * j]), h23 = Half2<T>::to_float2(hr[2 * j + 1]);
    if (gr) {
      const float4 g = gr[j];
      v[i] = make_float4(a.x + h01.x * g.x, a.y + h01.y * g.y, a.z + h23.x * g.z, a.w + h23.y * g.w);
    } else {
      v[i] = make_float4(a.x + h01.x, a.y + h01.y, a.z + h23.x, a.w + h23.y);
    }
    xo[j] = v[i];
  }
  layer_norm_affine_store<T, VPL>(v, lane, row, w, b, y, rows_per_w, eps);
}

// The (batch, token, head) item of this warp over B x L x H items of heads of D channels, and where it
// lies in a [B, L, 3, H, D] qkv tensor: bl = batch * L + token, hd = H * D (one of q, k, v of a token),
// off = h * D (the head within it), row = bl * 3 * hd + off (its q in qkv). False past the end.
struct TokenHead {
  int bi, l, h;
  int64_t bl, hd, off, row;
};
__device__ __forceinline__ void token_head(int64_t item, int L, int H, int D, TokenHead& th) {
  th.h = static_cast<int>(item % H);
  th.bl = item / H;
  th.l = static_cast<int>(th.bl % L);
  th.bi = static_cast<int>(th.bl / L);
  th.hd = static_cast<int64_t>(H) * D;
  th.off = static_cast<int64_t>(th.h) * D;
  th.row = th.bl * 3 * th.hd + th.off;
}
// The item of this warp (one warp per item); false past the end.
__device__ __forceinline__ bool token_head_of_warp(int B, int L, int H, int D, TokenHead& th) {
  const int64_t item = static_cast<int64_t>(blockIdx.x) * (blockDim.x / 32) + (threadIdx.x >> 5);
  if (item >= static_cast<int64_t>(B) * L * H) return false;
  token_head(item, L, H, D, th);
  return true;
}
// The item of this thread's group of G lanes (G = 8, 16 or 32: 32 / G items per warp) and whether it is
// real: lanes past the last item take the last one again (live = false) so that every lane of the warp
// joins the group's shuffles; they must not store.
template <int G>
__device__ __forceinline__ bool token_head_of_group(int B, int L, int H, int D, TokenHead& th) {
  const int64_t items = static_cast<int64_t>(B) * L * H;
  const int64_t item = (static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x) / G;
  const bool live = item < items;
  token_head(live ? item : items - 1, L, H, D, th);
  return live;
}

// One warp per (token, head); each lane handles D / 64 pairs of channels of q, k and v.
template <typename T, int PPL>
__global__ void split_qkv_rms_norm_kernel(const T* __restrict__ qkv, const float* __restrict__ gq,
                                          const float* __restrict__ gk, float scale, QkvOut q, QkvOut k, QkvOut v,
                                          int B, int L, int H) {
  const int lane = threadIdx.x & 31;
  TokenHead th;
  if (!token_head_of_warp(B, L, H, 64 * PPL, th)) return;
  const int l = th.l, bi = th.bi;
  const int64_t HD = th.hd, off = th.off;
  const typename Half2<T>::T2* src = reinterpret_cast<const typename Half2<T>::T2*>(qkv + th.row);
  // q and k: fp32 L2 norm over the head's D channels, then * gamma * scale, rounded once to T.
#pragma unroll
  for (int part = 0; part < 2; ++part) {
    const typename Half2<T>::T2* s = src + part * (HD / 2);
    float2 f[PPL];
    float ss = 0.f;
#pragma unroll
    for (int i = 0; i < PPL; ++i) {
      f[i] = Half2<T>::to_float2(s[lane + 32 * i]);
      ss += f[i].x * f[i].x + f[i].y * f[i].y;
    }
    const float inv = 1.f / fmaxf(sqrtf(warp_sum(ss)), 1e-12f);
    const float* g = (part == 0 ? gq : gk) + off;
    const QkvOut& o = part == 0 ? q : k;
    typename Half2<T>::T2* dst = reinterpret_cast<typename Half2<T>::T2*>(static_cast<T*>(o.ptr) + bi * o.sb + l * o.sl + off);
#pragma unroll
    for (int i = 0; i < PPL; ++i) {
      const int j = lane + 32 * i;
      dst[j] = Half2<T>::pack(f[i].x * inv * (g[2 * j] * scale), f[i].y * inv * (g[2 * j + 1] * scale));
    }
  }
  // v: copied.
  const typename Half2<T>::T2* sv = src + HD;
  typename Half2<T>::T2* dv = reinterpret_cast<typename Half2<T>::T2*>(static_cast<T*>(v.ptr) + bi * v.sb + l * v.sl + off);
#pragma unroll
  for (int i = 0; i < PPL; ++i) dv[lane + 32 * i] = sv[lane + 32 * i];
}


// Eight values of T in one 16-byte word: a lane's share of a head in the wide split kernels.
template <typename T>
struct Pack8 {
  using T2 = typename Half2<T>::T2;
  static __device__ __forceinline__ void unpack(const uint4& w, float (&f)[8]) {
    const T2* p = reinterpret_cast<const T2*>(&w);
#pragma unroll
    for (int i = 0; i < 4; ++i) {
      const float2 a = Half2<T>::to_float2(p[i]);
      f[2 * i] = a.x;
      f[2 * i + 1] = a.y;
    }
  }
  // (Built from 32-bit words so that the store stays one 16-byte instruction.)
  static __device__ __forceinline__ uint4 pack(const float (&f)[8]) {
    uint32_t u[4];
#pragma unroll
    for (int i = 0; i < 4; ++i) {
      const T2 p = Half2<T>::pack(f[2 * i], f[2 * i + 1]);
      u[i] = *reinterpret_cast<const uint32_t*>(&p);
    }
    return make_uint4(u[0], u[1], u[2], u[3]);
  }
};
// Eight fp32 gammas (two 16-byte loads) times scale, as the 4-byte kernels form them: g * scale.
__device__ __forceinline__ void gamma8(const float* g, float scale, float (&s)[8]) {
  const float4 a = reinterpret_cast<const float4*>(g)[0], b = reinterpret_cast<const float4*>(g)[1];
  s[0] = a.x * scale, s[1] = a.y * scale, s[2] = a.z * scale, s[3] = a.w * scale;
  s[4] = b.x * scale, s[5] = b.y * scale, s[6] = b.z * scale, s[7] = b.w * scale;
}
// Sum over the G consecutive lanes of a group (xor shuffles stay inside it); the whole warp must call.
template <int G>
__device__ __forceinline__ float group_sum(float v) {
#pragma unroll
  for (int o = G / 2; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffffu, v, o);
  return v;
}

// The q/k RMS norm of one (token, head) spread over a group of G lanes, 8 channels a lane:
// T(x / max(|x|, 1e-12) * (g * scale)), |x| in fp32 (the lane's 8 squares, then the group's sum).
template <typename T, int G>
__device__ __forceinline__ uint4 rms_norm8(const uint4& w, const float* g, float scale) {
  float x[8], gs[8];
  Pack8<T>::unpack(w, x);
  gamma8(g, scale, gs);
  float ss = 0.f;
#pragma unroll
  for (int i = 0; i < 8; ++i) ss += x[i] * x[i];
  const float inv = 1.f / fmaxf(sqrtf(group_sum<G>(ss)), 1e-12f);
#pragma unroll
  for (int i = 0; i < 8; ++i) x[i] = x[i] * inv * gs[i];
  return Pack8<T>::pack(x);
}

// split_qkv_rms_norm_kernel moving 16 bytes per lane and access: a group of G = 8 * P lanes per
// (token, head) of D = 64 * P channels (32 / G items per warp), 8 channels of q, k and v per lane, all
// three loads issued before the norms. Needs qkv, the gammas and the outputs 16-byte aligned and the
// output strides multiples of 8 elements (split_qkv_wide_ok). Values as the 4-byte kernel's up to the
// summation order of |x|.
template <typename T, int P>
__global__ void split_qkv_rms_norm_wide_kernel(const T* __restrict__ qkv, const float* __restrict__ gq,
                                               const float* __restrict__ gk, float scale, QkvOut q, QkvOut k, QkvOut v,
                                               int B, int L, int H) {
  constexpr int G = 8 * P;
  TokenHead th;
  const bool live = token_head_of_group<G>(B, L, H, 64 * P, th);
  const int64_t c = th.off + 8 * (threadIdx.x % G);  // this lane's first channel within q, k or v
  const uint4* src = reinterpret_cast<const uint4*>(qkv + th.row - th.off + c);
  const uint4 wq = src[0], wk = src[th.hd / 8], wv = src[th.hd / 4];
  const uint4 yq = rms_norm8<T, G>(wq, gq + c, scale), yk = rms_norm8<T, G>(wk, gk + c, scale);
  if (!live) return;
  // (__stwb: a plain write-back store, which keeps each one 16-byte wide.)
  auto at = [&](const QkvOut& o) { return reinterpret_cast<uint4*>(static_cast<T*>(o.ptr) + th.bi * o.sb + th.l * o.sl + c); };
  __stwb(at(q), yq);
  __stwb(at(k), yk);
  __stwb(at(v), wv);
}

// Backward of the LayerNorm + affine with respect to its input, for rows held by one warp each:
//   g = gy * w (fp32), xhat = (x - mean) * rstd,
//   dx = rstd * (g - mean(g) - xhat * mean(g * xhat)) [+ gx_in],
// and with dh: dh = dx * gate (bf16; gate null: dx), the gradient of the residual's sublayer output.
// mean and rstd are recomputed from x as in the forward. gy null: no LayerNorm gradient (dx = gx_in).
template <typename T, int VPL>
__global__ void layer_norm_affine_backward_kernel(const float* __restrict__ x, const float* __restrict__ w,
                                                  int64_t rows_per_w, const T* __restrict__ gy,
                                                  const float* __restrict__ gx_in, const float* __restrict__ gate,
                                                  int64_t rows_per_gate, float* __restrict__ dx,
                                                  T* __restrict__ dh, int64_t rows, float eps) {
  constexpr int C = 128 * VPL;
  const int lane = threadIdx.x & 31;
  const int64_t row = static_cast<int64_t>(blockIdx.x) * (blockDim.x / 32) + (threadIdx.x >> 5);
  if (row >= rows) return;
  float4 v[VPL], g[VPL];
  // LayerNorm gradient through the affine weight (zero when there is no incoming gradient).
  if (gy) {
    const float4* xr = reinterpret_cast<const float4*>(x + row * C);
    const float4* wv = reinterpret_cast<const float4*>(w + (row / rows_per_w) * C);
    const typename Half2<T>::T2* gr = reinterpret_cast<const typename Half2<T>::T2*>(gy + row * C);
#pragma unroll
    for (int i = 0; i < VPL; ++i) {
      const int j = lane + 32 * i;
      v[i] = xr[j];
      const float4 ww = wv[j];
      const float2 g01 = Half2<T>::to_float2(gr[2 * j]), g23 = Half2<T>::to_float2(gr[2 * j + 1]);
      g[i] = make_float4(g01.x * ww.x, g01.y * ww.y, g23.x * ww.z, g23.y * ww.w);
    }
    float mean, rstd;
    row_mean_rstd<VPL>(v, eps, mean, rstd);
    // xhat in place of x; sums of g and g * xhat.
    float sg = 0.f, sgx = 0.f;
#pragma unroll
    for (int i = 0; i < VPL; ++i) {
      v[i] = make_float4((v[i].x - mean) * rstd, (v[i].y - mean) * rstd, (v[i].z - mean) * rstd, (v[i].w - mean) * rstd);
      sg += (g[i].x + g[i].y) + (g[i].z + g[i].w);
      sgx += (g[i].x * v[i].x + g[i].y * v[i].y) + (g[i].z * v[i].z + g[i].w * v[i].w);
    }
    const float mg = warp_sum(sg) * (1.f / C), mgx = warp_sum(sgx) * (1.f / C);
#pragma unroll
    for (int i = 0; i < VPL; ++i)
      g[i] = make_float4(rstd * (g[i].x - mg - v[i].x * mgx), rstd * (g[i].y - mg - v[i].y * mgx),
                         rstd * (g[i].z - mg - v[i].z * mgx), rstd * (g[i].w - mg - v[i].w * mgx));
  } else {
#pragma unroll
    for (int i = 0; i < VPL; ++i) g[i] = make_float4(0.f, 0.f, 0.f, 0.f);
  }
  // Plus the gradient that reaches x directly; store dx (fp32) and dh = dx * gate (bf16).
  const float4* gi = gx_in ? reinterpret_cast<const float4*>(gx_in + row * C) : nullptr;
  const float4* gt = gate ? reinterpret_cast<const float4*>(gate + (row / rows_per_gate) * C) : nullptr;
  float4* dxr = reinterpret_cast<float4*>(dx + row * C);
  typename Half2<T>::T2* dhr = dh ? reinterpret_cast<typename Half2<T>::T2*>(dh + row * C) : nullptr;
#pragma unroll
  for (int i = 0; i < VPL; ++i) {
    const int j = lane + 32 * i;
    float4 d = g[i];
    if (gi) {
      const float4 a = gi[j];
      d = make_float4(d.x + a.x, d.y + a.y, d.z + a.z, d.w + a.w);
    }
    dxr[j] = d;
    if (dhr) {
      const float4 m = gt ? gt[j] : make_float4(1.f, 1.f, 1.f, 1.f);
      dhr[2 * j] = Half2<T>::pack(d.x * m.x, d.y * m.y);
      dhr[2 * j + 1] = Half2<T>::pack(d.z * m.z, d.w * m.w);
    }
  }
}

// Backward of split_qkv_rms_norm_kernel: one warp per (token, head). For q and k,
//   u = dy * gamma * scale, n = |x|: dx = u / n - x * (u . x) / n^3 (n > 1e-12; else u / 1e-12);
// v's gradient is copied. Incoming gradients are read through strides (null: zero).
template <typename T, int PPL>
__global__ void split_qkv_rms_norm_backward_kernel(const T* __restrict__ qkv, const float* __restrict__ gq,
                                                   const float* __restrict__ gk, float scale, QkvGrad dq, QkvGrad dk,
                                                   QkvGrad dv, T* __restrict__ dqkv, int B, int L, int H) {
  const int lane = threadIdx.x & 31;
  TokenHead th;
  if (!token_head_of_warp(B, L, H, 64 * PPL, th)) return;
  const int h = th.h, l = th.l, bi = th.bi;
  const int64_t HD = th.hd, off = th.off;
  const typename Half2<T>::T2* src = reinterpret_cast<const typename Half2<T>::T2*>(qkv + th.row);
  typename Half2<T>::T2* dst = reinterpret_cast<typename Half2<T>::T2*>(dqkv + th.row);
#pragma unroll
  for (int part = 0; part < 3; ++part) {
    const QkvGrad& gsrc = part == 0 ? dq : part == 1 ? dk : dv;
    typename Half2<T>::T2* o = dst + part * (HD / 2);
    const typename Half2<T>::T2* gp =
        gsrc.ptr ? reinterpret_cast<const typename Half2<T>::T2*>(static_cast<const T*>(gsrc.ptr) + bi * gsrc.sb + l * gsrc.sl + h * gsrc.sh) : nullptr;
    if (!gp) {
#pragma unroll
      for (int i = 0; i < PPL; ++i) o[lane + 32 * i] = Half2<T>::pack(0.f, 0.f);
      continue;
    }
    if (part == 2) {
#pragma unroll
      for (int i = 0; i < PPL; ++i) o[lane + 32 * i] = gp[lane + 32 * i];
      continue;
    }
    const typename Half2<T>::T2* s = src + part * (HD / 2);
    const float* g = (part == 0 ? gq : gk) + off;
    float2 xv[PPL], u[PPL];
    float ss = 0.f, ux = 0.f;
#pragma unroll
    for (int i = 0; i < PPL; ++i) {
      const int j = lane + 32 * i;
      xv[i] = Half2<T>::to_float2(s[j]);
      const float2 dy = Half2<T>::to_float2(gp[j]);
      u[i] = make_float2(dy.x * (g[2 * j] * scale), dy.y * (g[2 * j + 1] * scale));
      ss += xv[i].x * xv[i].x + xv[i].y * xv[i].y;
      ux += u[i].x * xv[i].x + u[i].y * xv[i].y;
    }
    const float n = sqrtf(warp_sum(ss));
    const float dot = warp_sum(ux);
    const bool clamped = !(n > 1e-12f);
    const float r = 1.f / (clamped ? 1e-12f : n);
    const float c = clamped ? 0.f : dot * r * r * r;
#pragma unroll
    for (int i = 0; i < PPL; ++i)
      o[lane + 32 * i] = Half2<T>::pack(u[i].x * r - xv[i].x * c, u[i].y * r - xv[i].y * c);
  }
}


// Backward of rms_norm8 for one (token, head) over a group of G lanes (formula of
// split_qkv_rms_norm_backward_kernel): u = dy * (g * scale), dx = u / n - x * (u . x) / n^3.
template <typename T, int G>
__device__ __forceinline__ uint4 rms_norm8_backward(const uint4& xw, const uint4& dyw, const float* g, float scale) {
  float x[8], u[8], gs[8];
  Pack8<T>::unpack(xw, x);
  Pack8<T>::unpack(dyw, u);
  gamma8(g, scale, gs);
  float ss = 0.f, ux = 0.f;
#pragma unroll
  for (int i = 0; i < 8; ++i) {
    u[i] = u[i] * gs[i];
    ss += x[i] * x[i];
    ux += u[i] * x[i];
  }
  const float n = sqrtf(group_sum<G>(ss));
  const float dot = group_sum<G>(ux);
  const bool clamped = !(n > 1e-12f);
  const float r = 1.f / (clamped ? 1e-12f : n);
  const float cc = clamped ? 0.f : dot * r * r * r;
#pragma unroll
  for (int i = 0; i < 8; ++i) u[i] = u[i] * r - x[i] * cc;
  return Pack8<T>::pack(u);
}

// split_qkv_rms_norm_backward_kernel moving 16 bytes per lane and access (groups of G = 8 * P lanes per
// (token, head), as split_qkv_rms_norm_wide_kernel); every load is issued before the reductions.
// Needs 16-byte aligned pointers and gradient strides multiple of 8 elements (split_qkv_backward_wide_ok).
template <typename T, int P>
__global__ void split_qkv_rms_norm_backward_wide_kernel(const T* __restrict__ qkv, const float* __restrict__ gq,
                                                        const float* __restrict__ gk, float scale, QkvGrad dq, QkvGrad dk,
                                                        QkvGrad dv, T* __restrict__ dqkv, int B, int L, int H) {
  constexpr int G = 8 * P;
  TokenHead th;
  const bool live = token_head_of_group<G>(B, L, H, 64 * P, th);
  const int64_t c = th.off + 8 * (threadIdx.x % G);
  const int64_t base = th.row - th.off + c;  // this lane's q channels in qkv / dqkv
  const uint4* src = reinterpret_cast<const uint4*>(qkv + base);
  auto grad = [&](const QkvGrad& gr) {
    return reinterpret_cast<const uint4*>(static_cast<const T*>(gr.ptr) + th.bi * gr.sb + th.l * gr.sl + th.h * gr.sh +
                                          (c - th.off));
  };
  // Loads first (a null gradient is not read: its part is zero).
  const uint4 zero = make_uint4(0u, 0u, 0u, 0u);
  const uint4 xq = dq.ptr ? src[0] : zero, xk = dk.ptr ? src[th.hd / 8] : zero;
  const uint4 gyq = dq.ptr ? *grad(dq) : zero, gyk = dk.ptr ? *grad(dk) : zero, gyv = dv.ptr ? *grad(dv) : zero;
  const uint4 oq = dq.ptr ? rms_norm8_backward<T, G>(xq, gyq, gq + c, scale) : zero;
  const uint4 ok = dk.ptr ? rms_norm8_backward<T, G>(xk, gyk, gk + c, scale) : zero;
  if (!live) return;
  uint4* dst = reinterpret_cast<uint4*>(dqkv + base);
  dst[0] = oq;
  dst[th.hd / 8] = ok;
  dst[th.hd / 4] = gyv;
}

// Scalar conversions of the modulation's storage types (round to nearest even, as ATen's casts).
template <typename T>
struct Scalar;
template <>
struct Scalar<__nv_bfloat16> {
  static __device__ __forceinline__ float to_float(__nv_bfloat16 v) { return __bfloat162float(v); }
  static __device__ __forceinline__ __nv_bfloat16 round(float v) { return __float2bfloat16_rn(v); }
};
template <>
struct Scalar<__half> {
  static __device__ __forceinline__ float to_float(__half v) { return __half2float(v); }
  static __device__ __forceinline__ __half round(float v) { return __float2half_rn(v); }
};
template <>
struct Scalar<float> {
  static __device__ __forceinline__ float to_float(float v) { return v; }
  static __device__ __forceinline__ float round(float v) { return v; }
};

// One thread per output element of [6, rows, C]: chunk k of row r, channel c.
template <typename T>
__global__ void modulation_rows_kernel(const T* __restrict__ m, float* __restrict__ out, int64_t rows, int64_t C) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const int64_t per_chunk = rows * C;
  if (i >= 6 * per_chunk) return;
  const int64_t k = i / per_chunk, r = (i % per_chunk) / C, c = i % C;
  const float v = Scalar<T>::to_float(m[r * 6 * C + k * C + c]);
  // The scales: 1 + scale in fp32 (ATen's opmath), rounded once to T, then widened.
  out[i] = (k == 1 || k == 4) ? Scalar<T>::to_float(Scalar<T>::round(v + 1.0f)) : v;
}
}  // namespace

namespace {

// Launches launch(std::integral_constant<int, V>) for the width the kernels are instantiated for:
// channels C = 128 * V (V in 1, 2, 4, 6, 8) ...
template <typename Launch>
cudaError_t by_channels(int C, Launch&& launch) {
  switch (C) {
    case 128: launch(std::integral_constant<int, 1>{}); break;
    case 256: launch(std::integral_constant<int, 2>{}); break;
    case 512: launch(std::integral_constant<int, 4>{}); break;
    case 768: launch(std::integral_constant<int, 6>{}); break;
    case 1024: launch(std::integral_constant<int, 8>{}); break;
    default: return cudaErrorInvalidValue;
  }
  return cudaGetLastError();
}
// ... or head dim D = 64 * P (P in 1, 2, 4).
template <typename Launch>
cudaError_t by_head_dim(int D, Launch&& launch) {
  switch (D) {
    case 64: launch(std::integral_constant<int, 1>{}); break;
    case 128: launch(std::integral_constant<int, 2>{}); break;
    case 256: launch(std::integral_constant<int, 4>{}); break;
    default: return cudaErrorInvalidValue;
  }
  return cudaGetLastError();
}

// One warp per item, 8 warps per block.
constexpr int kWarps = 8;
dim3 grid_for(int64_t items) { return dim3(static_cast<unsigned>((items + kWarps - 1) / kWarps)); }
const dim3 kBlock(32 * kWarps);

}  // namespace

template <typename T>
cudaError_t layer_norm_affine(const float* x, const float* w, const float* b, T* y, int64_t rows, int64_t rows_per_w,
                              int C, float eps, cudaStream_t stream) {
  return by_channels(C, [&](auto v) {
    layer_norm_affine_kernel<T, decltype(v)::value><<<grid_for(rows), kBlock, 0, stream>>>(x, w, b, y, rows, rows_per_w, eps);
  });
}

template <typename T>
cudaError_t residual_layer_norm_affine(const float* x, const T* h, int64_t h_rows, const T* h_tail, const float* gate,
                                       int64_t rows_per_gate, float* x_out, const float* w, const float* b, T* y,
                                       int64_t rows, int64_t rows_per_w, int C, float eps, cudaStream_t stream) {
  if (h_rows < rows && !h_tail) return cudaErrorInvalidValue;
  return by_channels(C, [&](auto v) {
    residual_layer_norm_affine_kernel<T, decltype(v)::value><<<grid_for(rows), kBlock, 0, stream>>>(
        x, h, h_rows, h_tail, gate, rows_per_gate, x_out, w, b, y, rows, rows_per_w, eps);
  });
}

namespace {
bool aligned16(const void* p) { return reinterpret_cast<uintptr_t>(p) % 16 == 0; }
// The wide kernels' grid: a group of 8 * P lanes per item, blocks of kBlock threads.
dim3 wide_grid_for(int64_t items, int P) { return dim3(static_cast<unsigned>((items * 8 * P + kBlock.x - 1) / kBlock.x)); }
}  // namespace

bool split_qkv_wide_ok(const void* qkv, const float* gq, const float* gk, QkvOut q, QkvOut k, QkvOut v) {
  auto out_ok = [](const QkvOut& o) { return aligned16(o.ptr) && o.sb % 8 == 0 && o.sl % 8 == 0; };
  return aligned16(qkv) && aligned16(gq) && aligned16(gk) && out_ok(q) && out_ok(k) && out_ok(v);
}

bool split_qkv_backward_wide_ok(const void* qkv, const float* gq, const float* gk, QkvGrad dq, QkvGrad dk, QkvGrad dv,
                                const void* dqkv) {
  auto grad_ok = [](const QkvGrad& g) {
    return !g.ptr || (aligned16(g.ptr) && g.sb % 8 == 0 && g.sl % 8 == 0 && g.sh % 8 == 0);
  };
  return aligned16(qkv) && aligned16(gq) && aligned16(gk) && aligned16(dqkv) && grad_ok(dq) && grad_ok(dk) && grad_ok(dv);
}

template <typename T>
cudaError_t split_qkv_rms_norm(const T* qkv, const float* gq, const float* gk, float scale, QkvOut q, QkvOut k, QkvOut v,
                               int B, int L, int H, int D, bool wide, cudaStream_t stream) {
  const int64_t items = static_cast<int64_t>(B) * L * H;
  if (items == 0) return cudaSuccess;
  if (wide && !split_qkv_wide_ok(qkv, gq, gk, q, k, v)) return cudaErrorMisalignedAddress;
  return by_head_dim(D, [&](auto p) {
    constexpr int P = decltype(p)::value;
    if (wide)
      split_qkv_rms_norm_wide_kernel<T, P><<<wide_grid_for(items, P), kBlock, 0, stream>>>(qkv, gq, gk, scale, q, k, v, B, L, H);
    else
      split_qkv_rms_norm_kernel<T, P><<<grid_for(items), kBlock, 0, stream>>>(qkv, gq, gk, scale, q, k, v, B, L, H);
  });
}

template <typename T>
cudaError_t layer_norm_affine_backward(const float* x, const float* w, int64_t rows_per_w, const T* gy, const float* gx_in,
                                       const float* gate, int64_t rows_per_gate, float* dx, T* dh, int64_t rows, int C,
                                       float eps, cudaStream_t stream) {
  return by_channels(C, [&](auto v) {
    layer_norm_affine_backward_kernel<T, decltype(v)::value><<<grid_for(rows), kBlock, 0, stream>>>(
        x, w, rows_per_w, gy, gx_in, gate, rows_per_gate, dx, dh, rows, eps);
  });
}

template <typename T>
cudaError_t split_qkv_rms_norm_backward(const T* qkv, const float* gq, const float* gk, float scale, QkvGrad dq, QkvGrad dk,
                                        QkvGrad dv, T* dqkv, int B, int L, int H, int D, bool wide, cudaStream_t stream) {
  const int64_t items = static_cast<int64_t>(B) * L * H;
  if (items == 0) return cudaSuccess;
  if (wide && !split_qkv_backward_wide_ok(qkv, gq, gk, dq, dk, dv, dqkv)) return cudaErrorMisalignedAddress;
  return by_head_dim(D, [&](auto p) {
    constexpr int P = decltype(p)::value;
    if (wide)
      split_qkv_rms_norm_backward_wide_kernel<T, P><<<wide_grid_for(items, P), kBlock, 0, stream>>>(
          qkv, gq, gk, scale, dq, dk, dv, dqkv, B, L, H);
    else
      split_qkv_rms_norm_backward_kernel<T, P><<<grid_for(items), kBlock, 0, stream>>>(qkv, gq, gk, scale, dq, dk, dv, dqkv,
                                                                                        B, L, H);
  });
}

template <typename T>
cudaError_t modulation_rows(const T* m, float* out, int64_t rows, int64_t C, cudaStream_t stream) {
  const int64_t n = 6 * rows * C;
  if (n == 0) return cudaSuccess;
  constexpr int kThreads = 256;
  modulation_rows_kernel<T><<<static_cast<unsigned>((n + kThreads - 1) / kThreads), kThreads, 0, stream>>>(m, out, rows, C);
  return cudaGetLastError();
}
template cudaError_t modulation_rows<__nv_bfloat16>(const __nv_bfloat16*, float*, int64_t, int64_t, cudaStream_t);
template cudaError_t modulation_rows<__half>(const __half*, float*, int64_t, int64_t, cudaStream_t);
template cudaError_t modulation_rows<float>(const float*, float*, int64_t, int64_t, cudaStream_t);

// The two storage types.
#define SIMU_INSTANTIATE(T)                                                                                              \
  template cudaError_t layer_norm_affine<T>(const float*, const float*, const float*, T*, int64_t, int64_t, int, float,  \
                                            cudaStream_t);                                                               \
  template cudaError_t residual_layer_norm_affine<T>(const float*, const T*, int64_t, const T*, const float*, int64_t,   \
                                                     float*, const float*, const float*, T*, int64_t, int64_t, int,     \
                                                     float, cudaStream_t);                                              \
  template cudaError_t split_qkv_rms_norm<T>(const T*, const float*, const float*, float, QkvOut, QkvOut, QkvOut, int,   \
                                             int, int, int, bool, cudaStream_t);                                         \
  template cudaError_t layer_norm_affine_backward<T>(const float*, const float*, int64_t, const T*, const float*,        \
                                                     const float*, int64_t, float*, T*, int64_t, int, float,             \
                                                     cudaStream_t);                                                      \
  template cudaError_t split_qkv_rms_norm_backward<T>(const T*, const float*, const float*, float, QkvGrad, QkvGrad,     \
                                                      QkvGrad, T*, int, int, int, int, bool, cudaStream_t);
SIMU_INSTANTIATE(__nv_bfloat16)
SIMU_INSTANTIATE(__half)
#undef SIMU_INSTANTIATE

}  // namespace simu::models::kernels
