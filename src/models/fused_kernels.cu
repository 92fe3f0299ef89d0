// Fused CUDA kernels of the flow model's inference path (see fused_kernels.h for the contracts).
#include "models/fused_kernels.h"

namespace simu::models::kernels {

namespace {

__device__ __forceinline__ float warp_sum(float v) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffffu, v, o);
  return v;
}

// The LayerNorm + affine of one row held in registers (lane's VPL float4; C = 128 * VPL) by one warp:
// mean and variance about the mean (two passes over registers, as torch's fp32 layer_norm), then
// y = (v - mean) * rstd * w + b stored as bf16.
template <int VPL>
__device__ __forceinline__ void layer_norm_affine_store(const float4 (&v)[VPL], int lane, int64_t row,
                                                        const float* __restrict__ w, const float* __restrict__ b,
                                                        __nv_bfloat16* __restrict__ y, int64_t rows_per_w, float eps) {
  constexpr int C = 128 * VPL;
  float s = 0.f;
#pragma unroll
  for (int i = 0; i < VPL; ++i) s += (v[i].x + v[i].y) + (v[i].z + v[i].w);
  const float mean = warp_sum(s) * (1.f / C);
  float q = 0.f;
#pragma unroll
  for (int i = 0; i < VPL; ++i) {
    const float a = v[i].x - mean, bb = v[i].y - mean, c = v[i].z - mean, d = v[i].w - mean;
    q += (a * a + bb * bb) + (c * c + d * d);
  }
  const float rstd = rsqrtf(warp_sum(q) * (1.f / C) + eps);
  // Affine (per-row-group weight and bias), store bf16.
  const int64_t wr = row / rows_per_w;
  const float4* wv = reinterpret_cast<const float4*>(w + wr * C);
  const float4* bv = b ? reinterpret_cast<const float4*>(b + wr * C) : nullptr;
  __nv_bfloat162* yr = reinterpret_cast<__nv_bfloat162*>(y + row * C);
#pragma unroll
  for (int i = 0; i < VPL; ++i) {
    const int j = lane + 32 * i;
    const float4 ww = wv[j];
    const float4 bb = bv ? bv[j] : make_float4(0.f, 0.f, 0.f, 0.f);
    const float o0 = (v[i].x - mean) * rstd * ww.x + bb.x, o1 = (v[i].y - mean) * rstd * ww.y + bb.y;
    const float o2 = (v[i].z - mean) * rstd * ww.z + bb.z, o3 = (v[i].w - mean) * rstd * ww.w + bb.w;
    yr[2 * j] = __floats2bfloat162_rn(o0, o1);
    yr[2 * j + 1] = __floats2bfloat162_rn(o2, o3);
  }
}

// One warp per row; each lane keeps VPL float4 of the row in registers (C = 128 * VPL).
template <int VPL>
__global__ void layer_norm_affine_bf16_kernel(const float* __restrict__ x, const float* __restrict__ w,
                                              const float* __restrict__ b, __nv_bfloat16* __restrict__ y, int64_t rows,
                                              int64_t rows_per_w, float eps) {
  constexpr int C = 128 * VPL;
  const int lane = threadIdx.x & 31;
  const int64_t row = static_cast<int64_t>(blockIdx.x) * (blockDim.x / 32) + (threadIdx.x >> 5);
  if (row >= rows) return;
  const float4* xr = reinterpret_cast<const float4*>(x + row * C);
  float4 v[VPL];
#pragma unroll
  for (int i = 0; i < VPL; ++i) v[i] = xr[lane + 32 * i];
  layer_norm_affine_store<VPL>(v, lane, row, w, b, y, rows_per_w, eps);
}

// layer_norm_affine_bf16_kernel with the residual update in front: x_out = x + h * gate (fp32), then
// the LayerNorm + affine of x_out stored as bf16. One warp per row, VPL float4 per lane.
template <int VPL>
__global__ void residual_layer_norm_affine_bf16_kernel(const float* __restrict__ x, const __nv_bfloat16* __restrict__ h,
                                                       const float* __restrict__ gate, int64_t rows_per_gate,
                                                       float* __restrict__ x_out, const float* __restrict__ w,
                                                       const float* __restrict__ b, __nv_bfloat16* __restrict__ y,
                                                       int64_t rows, int64_t rows_per_w, float eps) {
  constexpr int C = 128 * VPL;
  const int lane = threadIdx.x & 31;
  const int64_t row = static_cast<int64_t>(blockIdx.x) * (blockDim.x / 32) + (threadIdx.x >> 5);
  if (row >= rows) return;
  const float4* xr = reinterpret_cast<const float4*>(x + row * C);
  const __nv_bfloat162* hr = reinterpret_cast<const __nv_bfloat162*>(h + row * C);
  const float4* gr = gate ? reinterpret_cast<const float4*>(gate + (row / rows_per_gate) * C) : nullptr;
  float4* xo = reinterpret_cast<float4*>(x_out + row * C);
  // Residual update (x + h * gate, as addcmul computes it), written out.
  float4 v[VPL];
#pragma unroll
  for (int i = 0; i < VPL; ++i) {
    const int j = lane + 32 * i;
    const float4 a = xr[j];
    const float2 h01 = __bfloat1622float2(hr[2 * j]), h23 = __bfloat1622float2(hr[2 * j + 1]);
    if (gr) {
      const float4 g = gr[j];
      v[i] = make_float4(a.x + h01.x * g.x, a.y + h01.y * g.y, a.z + h23.x * g.z, a.w + h23.y * g.w);
    } else {
      v[i] = make_float4(a.x + h01.x, a.y + h01.y, a.z + h23.x, a.w + h23.y);
    }
    xo[j] = v[i];
  }
  layer_norm_affine_store<VPL>(v, lane, row, w, b, y, rows_per_w, eps);
}

// One warp per (token, head); each lane handles D / 64 pairs of channels of q, k and v.
template <int PPL>
__global__ void split_qkv_rms_norm_kernel(const __nv_bfloat16* __restrict__ qkv, const float* __restrict__ gq,
                                          const float* __restrict__ gk, float scale, QkvOut q, QkvOut k, QkvOut v,
                                          int B, int L, int H) {
  constexpr int D = 64 * PPL;
  const int lane = threadIdx.x & 31;
  const int64_t item = static_cast<int64_t>(blockIdx.x) * (blockDim.x / 32) + (threadIdx.x >> 5);
  if (item >= static_cast<int64_t>(B) * L * H) return;
  const int h = static_cast<int>(item % H);
  const int64_t bl = item / H;
  const int l = static_cast<int>(bl % L), bi = static_cast<int>(bl / L);
  const int64_t HD = static_cast<int64_t>(H) * D;
  const __nv_bfloat162* src = reinterpret_cast<const __nv_bfloat162*>(qkv + bl * 3 * HD + static_cast<int64_t>(h) * D);
  const int64_t off = static_cast<int64_t>(h) * D;
  // q and k: fp32 L2 norm over the head's D channels, then * gamma * scale, rounded once to bf16.
#pragma unroll
  for (int part = 0; part < 2; ++part) {
    const __nv_bfloat162* s = src + part * (HD / 2);
    float2 f[PPL];
    float ss = 0.f;
#pragma unroll
    for (int i = 0; i < PPL; ++i) {
      f[i] = __bfloat1622float2(s[lane + 32 * i]);
      ss += f[i].x * f[i].x + f[i].y * f[i].y;
    }
    const float inv = 1.f / fmaxf(sqrtf(warp_sum(ss)), 1e-12f);
    const float* g = (part == 0 ? gq : gk) + off;
    const QkvOut& o = part == 0 ? q : k;
    __nv_bfloat162* dst = reinterpret_cast<__nv_bfloat162*>(o.ptr + bi * o.sb + l * o.sl + off);
#pragma unroll
    for (int i = 0; i < PPL; ++i) {
      const int j = lane + 32 * i;
      dst[j] = __floats2bfloat162_rn(f[i].x * inv * (g[2 * j] * scale), f[i].y * inv * (g[2 * j + 1] * scale));
    }
  }
  // v: copied.
  const __nv_bfloat162* sv = src + HD;
  __nv_bfloat162* dv = reinterpret_cast<__nv_bfloat162*>(v.ptr + bi * v.sb + l * v.sl + off);
#pragma unroll
  for (int i = 0; i < PPL; ++i) dv[lane + 32 * i] = sv[lane + 32 * i];
}

}  // namespace

cudaError_t layer_norm_affine_bf16(const float* x, const float* w, const float* b, __nv_bfloat16* y, int64_t rows,
                                   int64_t rows_per_w, int C, float eps, cudaStream_t stream) {
  constexpr int warps = 8;
  const dim3 grid(static_cast<unsigned>((rows + warps - 1) / warps)), block(32 * warps);
  switch (C) {
    case 128: layer_norm_affine_bf16_kernel<1><<<grid, block, 0, stream>>>(x, w, b, y, rows, rows_per_w, eps); break;
    case 256: layer_norm_affine_bf16_kernel<2><<<grid, block, 0, stream>>>(x, w, b, y, rows, rows_per_w, eps); break;
    case 512: layer_norm_affine_bf16_kernel<4><<<grid, block, 0, stream>>>(x, w, b, y, rows, rows_per_w, eps); break;
    case 768: layer_norm_affine_bf16_kernel<6><<<grid, block, 0, stream>>>(x, w, b, y, rows, rows_per_w, eps); break;
    case 1024: layer_norm_affine_bf16_kernel<8><<<grid, block, 0, stream>>>(x, w, b, y, rows, rows_per_w, eps); break;
    default: return cudaErrorInvalidValue;
  }
  return cudaGetLastError();
}

cudaError_t residual_layer_norm_affine_bf16(const float* x, const __nv_bfloat16* h, const float* gate,
                                            int64_t rows_per_gate, float* x_out, const float* w, const float* b,
                                            __nv_bfloat16* y, int64_t rows, int64_t rows_per_w, int C, float eps,
                                            cudaStream_t stream) {
  constexpr int warps = 8;
  const dim3 grid(static_cast<unsigned>((rows + warps - 1) / warps)), block(32 * warps);
#define SIMU_RLN(VPL) \
  residual_layer_norm_affine_bf16_kernel<VPL><<<grid, block, 0, stream>>>(x, h, gate, rows_per_gate, x_out, w, b, y, rows, rows_per_w, eps)
  switch (C) {
    case 128: SIMU_RLN(1); break;
    case 256: SIMU_RLN(2); break;
    case 512: SIMU_RLN(4); break;
    case 768: SIMU_RLN(6); break;
    case 1024: SIMU_RLN(8); break;
    default: return cudaErrorInvalidValue;
  }
#undef SIMU_RLN
  return cudaGetLastError();
}

cudaError_t split_qkv_rms_norm(const __nv_bfloat16* qkv, const float* gq, const float* gk, float scale, QkvOut q,
                               QkvOut k, QkvOut v, int B, int L, int H, int D, cudaStream_t stream) {
  constexpr int warps = 8;
  const int64_t items = static_cast<int64_t>(B) * L * H;
  const dim3 grid(static_cast<unsigned>((items + warps - 1) / warps)), block(32 * warps);
  switch (D) {
    case 64: split_qkv_rms_norm_kernel<1><<<grid, block, 0, stream>>>(qkv, gq, gk, scale, q, k, v, B, L, H); break;
    case 128: split_qkv_rms_norm_kernel<2><<<grid, block, 0, stream>>>(qkv, gq, gk, scale, q, k, v, B, L, H); break;
    case 256: split_qkv_rms_norm_kernel<4><<<grid, block, 0, stream>>>(qkv, gq, gk, scale, q, k, v, B, L, H); break;
    default: return cudaErrorInvalidValue;
  }
  return cudaGetLastError();
}

}  // namespace simu::models::kernels
