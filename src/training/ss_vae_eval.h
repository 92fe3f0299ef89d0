// Reconstruction quality of a sparse-structure VAE: the per-sample loss terms it trains on and the IoU
// of the decoded occupancy (logits > 0) against the input grid, per shape and as a per-family table.
#pragma once

#include <torch/torch.h>

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "models/ss_decoder.h"
#include "models/ss_encoder.h"
#include "training/ss_vae_config.h"
#include "training/ss_vae_data.h"

namespace simu::training {

// Per-sample terms of the VAE loss, each [B] float32 (a mean over the sample's voxels or latent elements).
struct SsVaeTerms {
  torch::Tensor bce, dice, l1, kl;  // as SsVaeLossConfig describes them
  torch::Tensor total;              // bce*w_bce + dice*w_dice + l1*w_l1 + lambda_kl*kl
  torch::Tensor iou;                // IoU of logits > 0 with the grid (no gradient; 1 when both are empty)
};
// logits, occupancy (0/1): [B, 1, R, R, R] float32; mean, logvar: [B, C, r, r, r] float32.
SsVaeTerms ss_vae_terms(const torch::Tensor& logits, const torch::Tensor& occupancy, const torch::Tensor& mean,
                        const torch::Tensor& logvar, const SsVaeLossConfig& loss);

// IoU per sample of (logits > 0) against occupancy > 0: [B, 1, R, R, R] each -> [B] float32.
torch::Tensor occupancy_iou(const torch::Tensor& logits, const torch::Tensor& occupancy);

// Reconstructs shapes with the posterior mean (no sampling, as TRELLIS's snapshots) and returns each
// shape's IoU, in the order of `keys`. Grids are made on `workers` threads; forwards of `batch` shapes
// on the encoder's device, in bf16 autocast when bf16 (CUDA only).
std::vector<double> reconstruction_iou(models::SparseStructureEncoderImpl& encoder,
                                       models::SparseStructureDecoderImpl& decoder, const ShapeSet& shapes,
                                       const std::vector<ShapeKey>& keys, int64_t batch, int workers, bool bf16);

// IoU by family: one row per family (in the order they first appear), then the mean over the shapes
// of every family but the held-out one ("seen") and over the held-out family's ("held out").
struct IouTable {
  struct Row {
    std::string family;
    int64_t n = 0;
    double mean = 0, min = 0, median = 0;
    bool held_out = false;
  };
  std::vector<Row> rows;
  int64_t n_seen = 0, n_held_out = 0;
  double mean_seen = 0, mean_held_out = 0;  // NaN when there is no such shape
  // {"families": [{family, n, iou_mean, iou_min, iou_median, held_out}], "seen": {n, iou_mean},
  //  "held_out": {n, iou_mean}}
  nlohmann::json to_json() const;
  // A Markdown table (family | n | mean | median | min), then the seen / held-out means.
  std::string markdown() const;
};
IouTable iou_table(const std::vector<ShapeKey>& keys, const std::vector<double>& iou, const std::string& held_out_family);

}  // namespace simu::training
