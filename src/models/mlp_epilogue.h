// The flow model's frozen feed-forward net (fc1 -> GELU(tanh) -> fc2, flow_model.h FeedForwardNet) for
// training under CUDA bf16/fp16 autocast, with the GELU and its gradient in cuBLASLt matmul epilogues:
//   forward:  [h, pre] = fc1 as one cuBLASLt product with epilogue GELU_AUX_BIAS: h = gelu_tanh(x W1^T + b1)
//             and the pre-activation pre = x W1^T + b1 (the "aux" output), both 16-bit; y = h W2^T + b2
//             (addmm, as fc2 computes today).
//   backward: dPre = (dY W2) * gelu_tanh'(pre) as one cuBLASLt product with epilogue DGELU reading the aux,
//             then dX = dPre W1. No weight or bias gradients: the weights are frozen.
// This replaces ATen's separate GELU forward kernel (one read and one write of [rows, 4C]) and its backward
// kernel (two reads and one write) by an extra 16-bit store in fc1's epilogue and an extra load in the
// backward product's epilogue. cuBLASLt's GELU is the tanh approximation, the official
// nn.GELU(approximate="tanh").
//
// Reference path: mlp_reference (addmm -> gelu(tanh) -> addmm in plain ATen, differentiable), which the
// module takes wherever this one does not apply; tests/models/mlp_epilogue_gpu.cpp compares them (values,
// input gradients, aux). A forward without a graph (FM-DPO's reference pass) runs the same products as one
// with a graph (same epilogue, same cached algorithm; the aux is written and dropped), so both give the
// same bits. Sampling keeps the inference-only GELU_BIAS epilogue (fused_ops.h linear_gelu_tanh_bf16).
#pragma once

#include <torch/torch.h>

namespace simu::models {
class LinearImpl;
}

namespace simu::models::mlp_epilogue {

// True when the library was built against cublasLt.h and the process has LibTorch's libcublasLt loaded
// (its functions are looked up at run time, never linked: one cuBLASLt per process, torch's).
bool compiled();
// cuBLASLt epilogue products run so far in this process (forward GELU_AUX_BIAS and backward DGELU each
// count one); tests check that the fast path really ran. Counted apart from fused::launch_count.
int64_t launch_count();
// The fast path's switch (on by default; process-wide): off, frozen_mlp always declines and the module
// takes the ATen reference path (benchmarks compare the two in one run: bench_fmdpo --mlp-epilogue).
void set_enabled(bool on);
bool enabled();

// Which of cuBLASLt's heuristic algorithms the epilogue products run, per epilogue (fc1's GELU_AUX_BIAS,
// the backward's DGELU; process-wide, default 0 and 0: the heuristic's first). Rank k takes the k-th entry
// of the heuristic's list (best first) where the list has one, else the first. The choice is fixed per
// rank, problem and machine (no timing), so every process runs the same kernels and gets the same bits;
// benchmarks compare ranks (bench_mlp_epilogue --candidates, bench_fmdpo --lt-algo-ranks). Ranks: 0..15.
void set_algo_ranks(int gelu_aux, int dgelu);
std::pair<int, int> algo_ranks();
// The algorithm of the last epilogue product set up in this process (for benchmark tables): the rank it took,
// how many the heuristic offered, and its configuration (algorithm id, tile, stages, split-K, swizzle,
// cluster ids as cuBLASLt numbers them). Empty before the first product or without cuBLASLt.
struct AlgoInfo {
  int rank = -1;
  int found = 0;
  std::string config;
};
AlgoInfo last_algo();

// Whether mlp can take these operands: compiled, CUDA, x2: [rows >= 1, K] contiguous bf16/fp16; w1: [N, K],
// b1: [N], w2: [C, N], b2: [C], all contiguous in x2's dtype on its device; K, N, C multiples of 8 (16-byte
// rows, the aux leading dimension rule); every pointer 16-byte aligned.
bool supports(const torch::Tensor& x2, const torch::Tensor& w1, const torch::Tensor& b1, const torch::Tensor& w2,
              const torch::Tensor& b2);

// fc1 with the GELU epilogue: x2 [rows, K], w1 [N, K], b1 [N] (supports) -> {h, pre}, both [rows, N] in x2's dtype,
// h = gelu_tanh(pre). Without a cuBLASLt algorithm for the problem: addmm and ATen's gelu (same outputs up to
// rounding), counted as no launch.
std::pair<torch::Tensor, torch::Tensor> linear_gelu_aux(const torch::Tensor& x2, const torch::Tensor& w1,
                                                        const torch::Tensor& b1);
// The backward product with the DGELU epilogue: dy [rows, C], w2 [C, N], pre [rows, N] (linear_gelu_aux's)
// -> dPre = (dy w2) * gelu_tanh'(pre) [rows, N]. Without an algorithm: mm and ATen's gelu_backward.
torch::Tensor linear_dgelu(const torch::Tensor& dy, const torch::Tensor& w2, const torch::Tensor& pre);

// y = fc2(gelu_tanh(fc1(x))) through the epilogues, differentiable with respect to x only.
//   x: [..., K] bf16 or fp16; w1 [N, K], b1 [N], w2 [C, N], b2 [C] in x's dtype (no gradient) -> [..., C].
// Undefined when the operands are not supported (the caller then takes the reference).
torch::Tensor mlp(const torch::Tensor& x, const torch::Tensor& w1, const torch::Tensor& b1, const torch::Tensor& w2,
                  const torch::Tensor& b2);
// The plain-ATen reference: addmm -> gelu(approximate="tanh") -> addmm in x's dtype (differentiable in all).
torch::Tensor mlp_reference(const torch::Tensor& x, const torch::Tensor& w1, const torch::Tensor& b1,
                            const torch::Tensor& w2, const torch::Tensor& b2);

// The module's entry point: fc2(gelu_tanh(fc1(x))) through mlp for a frozen base under CUDA bf16/fp16
// autocast: x on CUDA (cast to the autocast dtype), weights from each Linear's product_weights (its compute
// copy where it applies, else cast), both with a bias. Undefined (take the ATen path) when anything is
// unsupported: no cuBLASLt, no 16-bit CUDA autocast, a weight or bias that requires a gradient, an adapter
// (enabled or not: a policy forward with adapters on and a reference forward with them off must take the
// same path) or an FP8 weight on fc1 or fc2, shapes or alignment (supports).
torch::Tensor frozen_mlp(const torch::Tensor& x, LinearImpl& fc1, LinearImpl& fc2);

}  // namespace simu::models::mlp_epilogue
