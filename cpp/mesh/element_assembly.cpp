#include "mesh/element_assembly.h"

#include <algorithm>
#include <string>
#include <type_traits>
#include <utility>

#include "core/errors.h"
#include "core/parallel.h"

namespace kinema {

ElementAssembly::ElementAssembly(Index vertex_count, int d, int k, const Index* elements,
                                 Index element_count)
    : vertex_count_(vertex_count), element_count_(element_count), d_(d), k_(k) {
  if (vertex_count < 1) throw InvalidArgument("vertices: expected at least one vertex");
  for (Index e = 0; e < element_count; ++e) {
    for (int a = 0; a < k; ++a) {
      const Index v = elements[e * k + a];
      if (v < 0 || v >= vertex_count)
        throw InvalidArgument("elements: element " + std::to_string(e) + " refers to vertex " +
                              std::to_string(v) + ", outside [0, " +
                              std::to_string(vertex_count) + ")");
      for (int b = 0; b < a; ++b)
        if (elements[e * k + b] == v)
          throw InvalidArgument("elements: element " + std::to_string(e) +
                                " repeats vertex " + std::to_string(v));
    }
  }

  // Vertex -> element slots (counting sort keeps element order).
  vertex_ptr_.assign(vertex_count + 1, 0);
  for (Index s = 0; s < element_count * k; ++s) ++vertex_ptr_[elements[s] + 1];
  for (Index i = 0; i < vertex_count; ++i) vertex_ptr_[i + 1] += vertex_ptr_[i];
  vertex_slot_.resize(element_count * k);
  {
    std::vector<Index> fill(vertex_ptr_.begin(), vertex_ptr_.end() - 1);
    for (Index s = 0; s < element_count * k; ++s) vertex_slot_[fill[elements[s]]++] = s;
  }

  // Block pattern: for vertex row i, the sorted neighbour set (i included) and the element
  // blocks (e, a, b) with elements[e][a] = i, elements[e][b] = neighbour, each stored as the
  // offset of its (0, 0) entry in the row-major element matrices (no division when gathering).
  const Index kd = Index(k) * d;
  block_ptr_.assign(vertex_count + 1, 0);
  std::vector<std::vector<std::pair<Index, Index>>> rows(vertex_count);  // (col, source)
  parallel_for(vertex_count, [&](Index i) {
    auto& row = rows[i];
    row.emplace_back(i, -1);  // the diagonal block exists even for an isolated vertex
    for (Index p = vertex_ptr_[i]; p < vertex_ptr_[i + 1]; ++p) {
      const Index e = vertex_slot_[p] / k, a = vertex_slot_[p] % k;
      for (int b = 0; b < k; ++b)
        row.emplace_back(elements[e * k + b], e * kd * kd + a * d * kd + b * d);
    }
    std::sort(row.begin(), row.end());
  });
  source_ptr_.push_back(0);
  for (Index i = 0; i < vertex_count; ++i) {
    const auto& row = rows[i];
    for (size_t q = 0; q < row.size(); ++q) {
      if (q == 0 || row[q].first != row[q - 1].first) {
        if (q > 0) source_ptr_.push_back(static_cast<Index>(source_.size()));
        block_col_.push_back(row[q].first);
      }
      if (row[q].second >= 0) source_.push_back(row[q].second);
    }
    source_ptr_.push_back(static_cast<Index>(source_.size()));
    block_ptr_[i + 1] = static_cast<Index>(block_col_.size());
    rows[i].clear();
    rows[i].shrink_to_fit();
  }

  // Dof-level CSR: dof row (i, r) holds, for each neighbour block j, the d columns (j, 0..d-1).
  const Index n = vertex_count * d;
  row_ptr_.assign(n + 1, 0);
  for (Index i = 0; i < vertex_count; ++i) {
    const Index len = (block_ptr_[i + 1] - block_ptr_[i]) * d;
    for (int r = 0; r < d; ++r) row_ptr_[i * d + r + 1] = len;
  }
  for (Index q = 0; q < n; ++q) row_ptr_[q + 1] += row_ptr_[q];
  col_index_.resize(row_ptr_[n]);
  diagonal_.resize(n);
  parallel_for(vertex_count, [&](Index i) {
    for (int r = 0; r < d; ++r) {
      Index pos = row_ptr_[i * d + r];
      for (Index b = block_ptr_[i]; b < block_ptr_[i + 1]; ++b)
        for (int c = 0; c < d; ++c) {
          if (block_col_[b] == i && c == r) diagonal_[i * d + r] = pos;
          col_index_[pos++] = block_col_[b] * d + c;
        }
    }
  });
}

void ElementAssembly::gather_vector(const Scalar* element_vectors, Scalar* out) const {
  // Each vertex sums its slots in order into registers (D known at compile time), then stores:
  // the same additions in the same order as summing into out, without a load and store per slot.
  const auto gather = [&](auto dim) {
    constexpr int D = decltype(dim)::value;
    parallel_for(vertex_count_, [&](Index i) {
      Scalar sum[D] = {};
      for (Index p = vertex_ptr_[i]; p < vertex_ptr_[i + 1]; ++p) {
        const Scalar* f = element_vectors + vertex_slot_[p] * D;  // slot e*k+a -> offset (e*k+a)*d
        for (int r = 0; r < D; ++r) sum[r] += f[r];
      }
      for (int r = 0; r < D; ++r) out[i * D + r] = sum[r];
    });
  };
  if (d_ == 2) return gather(std::integral_constant<int, 2>());
  if (d_ == 3) return gather(std::integral_constant<int, 3>());
  const int d = d_;
  parallel_for(vertex_count_, [&](Index i) {
    for (int r = 0; r < d; ++r) out[i * d + r] = 0;
    for (Index p = vertex_ptr_[i]; p < vertex_ptr_[i + 1]; ++p) {
      const Scalar* f = element_vectors + vertex_slot_[p] * d;  // slot e*k+a -> offset (e*k+a)*d
      for (int r = 0; r < d; ++r) out[i * d + r] += f[r];
    }
  });
}

void ElementAssembly::gather_matrix(const Scalar* element_matrices, Scalar* values) const {
  const int d = d_;
  const Index kd = Index(k_) * d;
  parallel_for(vertex_count_, [&](Index i) {
    for (Index b = block_ptr_[i]; b < block_ptr_[i + 1]; ++b) {
      const Index local = b - block_ptr_[i];
      for (int r = 0; r < d; ++r)
        for (int c = 0; c < d; ++c) {
          Scalar s = 0;
          for (Index q = source_ptr_[b]; q < source_ptr_[b + 1]; ++q)
            s += element_matrices[source_[q] + r * kd + c];
          values[row_ptr_[i * d + r] + local * d + c] = s;
        }
    }
  });
}

}  // namespace kinema
