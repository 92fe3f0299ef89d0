// Counting autograd nodes by name in the graph behind a tensor (tests that a path copies nothing).
#pragma once

#include <torch/torch.h>

#include <functional>
#include <string>
#include <unordered_set>

namespace simu::testing {

// Nodes named `name` (e.g. "CloneBackward0") in the graph behind t.
inline int count_graph_nodes(const torch::Tensor& t, const std::string& name) {
  std::unordered_set<torch::autograd::Node*> seen;
  std::function<int(const std::shared_ptr<torch::autograd::Node>&)> walk = [&](const auto& node) -> int {
    if (!node || !seen.insert(node.get()).second) return 0;
    int n = node->name() == name ? 1 : 0;
    for (const auto& e : node->next_edges()) n += walk(e.function);
    return n;
  };
  return walk(t.grad_fn());
}

}  // namespace simu::testing
