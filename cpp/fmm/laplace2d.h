// The 2D Laplace potential of point charges and its gradient,
//   phi(x) = sum_j q_j log|x - y_j|,   grad phi(x) = sum_j q_j (x - y_j) / |x - y_j|^2,
// by the adaptive fast multipole method (Greengard & Rokhlin 1987; Carrier, Greengard &
// Rokhlin 1988) in O(N + M) work, or by the direct O(N M) sum. Pairs at distance zero (the
// self term when targets are the sources, and coincident points) are left out of both.
#pragma once

#include "core/interrupt.h"
#include "core/types.h"

namespace kinema::fmm {

struct Laplace2dConfig {
  Scalar eps = 1e-10;     // relative 2-norm error asked for phi (and the gradient)
  bool gradient = false;  // also compute grad phi
  int order = 0;          // expansion order p; 0: chosen from eps
  Index leaf_size = 0;    // most sources or targets in a leaf; 0: chosen from the order
};

struct Laplace2dStats {
  int order = 0;
  Index leaf_size = 0;
  Index box_count = 0;
  int depth = 0;
  double seconds_tree = 0, seconds_upward = 0, seconds_downward = 0, seconds_leaves = 0;
};

// Expansion order that meets eps (measured over uniform, clustered and curve distributions).
int order_for(Scalar eps);
// Leaf size that balances direct sums against translations for order p.
Index leaf_size_for(int order);

// sources: n x 2 (row-major x, y), charges: n; targets: m x 2, or nullptr for the sources
// themselves (then m must equal n). phi: m outputs; grad: m x 2 outputs when config.gradient.
Laplace2dStats laplace2d(const Scalar* sources, const Scalar* charges, Index n,
                         const Scalar* targets, Index m, const Laplace2dConfig& config,
                         Scalar* phi, Scalar* grad, Interrupt& interrupt);

// The same sums directly (the exact reference), parallel over targets.
void direct2d(const Scalar* sources, const Scalar* charges, Index n, const Scalar* targets,
              Index m, bool gradient, Scalar* phi, Scalar* grad, Interrupt& interrupt);

}  // namespace kinema::fmm
