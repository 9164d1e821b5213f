// The single place that fixes kinema's scalar and index types and the memory layout shared
// with numpy. Zero-copy contract: every array crossing the Python boundary is C-contiguous
// float64 (Scalar) or int64 (Index); a grid of shape (nx, ny[, nz]) indexed [i, j(, k)] is
// stored with k fastest, then j, then i (numpy's C order), i.e. flat = (i*ny + j)*nz + k.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <cstdint>

namespace kinema {

using Scalar = double;
using Index = std::int64_t;

using VectorX = Eigen::Matrix<Scalar, Eigen::Dynamic, 1>;
using MatrixX = Eigen::Matrix<Scalar, Eigen::Dynamic, Eigen::Dynamic>;
using MatrixXRowMajor = Eigen::Matrix<Scalar, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using VectorMap = Eigen::Map<VectorX>;
using ConstVectorMap = Eigen::Map<const VectorX>;
// Compressed sparse storage with 64-bit indices, as CHOLMOD's "long" interface expects.
using SparseMatrix = Eigen::SparseMatrix<Scalar, Eigen::RowMajor, Index>;

}  // namespace kinema
