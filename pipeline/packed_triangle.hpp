// Packed storage of symmetric N x N matrices: N (N + 1) / 2 doubles instead of N^2 (memory per
// tracked spacecraft: a filter state holds 9 x 9 and 11 x 11 ones, design.md "< 4 KB"), the
// upper triangle row by row; (i, j) with i <= j is at packed_index(i, j). Unpacking gives back
// exactly the matrix packed when it was symmetric. The copies are straight-line code with
// compile-time positions (run-time loops of a few elements became string instructions whose
// start-up cost more than the copy).
#pragma once

#include <cstddef>
#include <type_traits>
#include <utility>

#include <Eigen/Core>

namespace magcal {

template <int N>
using PackedTriangle = Eigen::Matrix<double, N*(N + 1) / 2, 1>;

template <int N>
constexpr int packed_index(int i, int j) {  // i <= j
  return i * N - i * (i - 1) / 2 + (j - i);
}

namespace packed_triangle_detail {

// Row and column of the k-th packed element (upper triangle, row by row).
template <int N>
constexpr int packed_row(int k) {
  int i = 0;
  while (packed_index<N>(i, N - 1) < k) ++i;
  return i;
}
template <int N>
constexpr int packed_col(int k) {
  const int i = packed_row<N>(k);
  return i + (k - packed_index<N>(i, i));
}

// f(k, i, j) for every packed element, with k, i and j constants.
template <int N, typename F, std::size_t... K>
void for_each_packed(F&& f, std::index_sequence<K...>) {
  (f(static_cast<int>(K), std::integral_constant<int, packed_row<N>(static_cast<int>(K))>::value,
     std::integral_constant<int, packed_col<N>(static_cast<int>(K))>::value),
   ...);
}
template <int N, typename F>
void for_each_packed(F&& f) {
  for_each_packed<N>(f, std::make_index_sequence<N*(N + 1) / 2>{});
}

// Always inlined: an out-of-line copy would call f through a reference for every column.
template <int N, bool Reversed, typename F, int... K>
[[gnu::always_inline]] inline void for_each_column(F&& f, std::integer_sequence<int, K...>) {
  (f(std::integral_constant<int, (Reversed ? N - 1 - K : K)>{}), ...);
}

}  // namespace packed_triangle_detail

// The upper triangle of M (all of a symmetric M).
template <int N, typename Derived>
PackedTriangle<N> packed_upper(const Eigen::MatrixBase<Derived>& M) {
  static_assert(Derived::RowsAtCompileTime == N && Derived::ColsAtCompileTime == N);
  PackedTriangle<N> p;
  packed_triangle_detail::for_each_packed<N>([&](int k, int i, int j) { p(k) = M(i, j); });
  return p;
}

template <int N>
Eigen::Matrix<double, N, N> symmetric_from_packed(const PackedTriangle<N>& p) {
  Eigen::Matrix<double, N, N> M;
  packed_triangle_detail::for_each_packed<N>(
      [&](int k, int i, int j) { M(i, j) = M(j, i) = p(k); });
  return M;
}

// f(std::integral_constant<int, k>{}) for the columns k = 0..N-1 of an N x N matrix (or N-1..0):
// per-sample loops over a triangle as straight-line code with compile-time bounds (as run-time
// loops they were vectorised with alias checks and remainder branches that cost more than the
// arithmetic).
inline constexpr bool kLastToFirst = true;
template <int N, bool Reversed = false, typename F>
[[gnu::always_inline]] inline void for_each_column(F&& f) {
  packed_triangle_detail::for_each_column<N, Reversed>(f, std::make_integer_sequence<int, N>{});
}

// p += u u^T (packed), one multiply-add per element at a compile-time position.
template <int N, typename Derived>
void add_outer_product(PackedTriangle<N>& p, const Eigen::MatrixBase<Derived>& u) {
  static_assert(Derived::SizeAtCompileTime == N);
  packed_triangle_detail::for_each_packed<N>([&](int k, int i, int j) { p(k) += u(i) * u(j); });
}

}  // namespace magcal
