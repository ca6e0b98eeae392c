// Packed storage of symmetric and lower-triangular N x N matrices: N (N + 1) / 2 doubles instead
// of N^2 (memory per tracked spacecraft: a filter state holds 9 x 9 and 11 x 11 ones, design.md
// "< 4 KB"). The order is the upper triangle row by row, which is the lower triangle column by
// column: (i, j) with i <= j, or (j, i) of a lower-triangular matrix, is at packed_index(i, j).
// Unpacking gives back exactly the matrix packed when it was symmetric (lower triangular).
#pragma once

#include <Eigen/Core>

namespace magcal {

template <int N>
using PackedTriangle = Eigen::Matrix<double, N*(N + 1) / 2, 1>;

template <int N>
constexpr int packed_index(int i, int j) {  // i <= j
  return i * N - i * (i - 1) / 2 + (j - i);
}

// The upper triangle of M (all of a symmetric M).
template <int N, typename Derived>
PackedTriangle<N> packed_upper(const Eigen::MatrixBase<Derived>& M) {
  static_assert(Derived::RowsAtCompileTime == N && Derived::ColsAtCompileTime == N);
  PackedTriangle<N> p;
  for (int i = 0, k = 0; i < N; ++i) {
    for (int j = i; j < N; ++j) p(k++) = M(i, j);
  }
  return p;
}

template <int N>
Eigen::Matrix<double, N, N> symmetric_from_packed(const PackedTriangle<N>& p) {
  Eigen::Matrix<double, N, N> M;
  for (int i = 0, k = 0; i < N; ++i) {
    for (int j = i; j < N; ++j, ++k) M(i, j) = M(j, i) = p(k);
  }
  return M;
}

// The lower triangle of L (a Cholesky factor; nothing above the diagonal is kept).
template <int N, typename Derived>
PackedTriangle<N> packed_lower(const Eigen::MatrixBase<Derived>& L) {
  return packed_upper<N>(L.transpose());
}

// The lower-triangular matrix, zeros above the diagonal.
template <int N>
Eigen::Matrix<double, N, N> lower_from_packed(const PackedTriangle<N>& p) {
  Eigen::Matrix<double, N, N> L;
  for (int j = 0, k = 0; j < N; ++j) {
    for (int i = 0; i < j; ++i) L(i, j) = 0.0;
    for (int i = j; i < N; ++i) L(i, j) = p(k++);
  }
  return L;
}

}  // namespace magcal
