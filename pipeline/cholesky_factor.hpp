// Operations on the lower Cholesky factor S of a 9 x 9 covariance (P = S S^T) that the
// square-root filters need per sample: fixed size, no allocation, lower triangle only.
#pragma once

#include "pipeline/calibration_types.hpp"
#include "pipeline/packed_triangle.hpp"

namespace magcal {

// L v for a lower triangular L (the entries above the diagonal are not read): 45 multiply-adds,
// no call into Eigen's general matrix-vector kernel (which zeroes its result first and reads all
// 81 entries).
inline Vector9d lower_triangular_times(const Matrix9d& L, const Vector9d& v) {
  Vector9d out;
  for_each_column<9>([&](auto row) {  // row by row: each sum stays in a register
    constexpr int i = decltype(row)::value;
    double sum = 0.0;
    for (int j = 0; j <= i; ++j) sum += L(i, j) * v(j);
    out(i) = sum;
  });
  return out;
}

// Rank-1 Cholesky downdate of the lower factor S in place, given the whitened vector
// p = S^-1 u: S S^T - u u^T = S (I - p p^T) S^T. Returns false, S untouched, when |p| >= 1
// (the result would not be positive definite). O(n^2), no allocation, no serial sqrt chain.
// Reads and writes the lower triangle only (above it S must be zero, as a Cholesky factor is).
bool cholesky_downdate_whitened(Matrix9d& S, const Vector9d& p);
// The same given S_p = S p (a filter has it: S_p is its Pxz / sqrt(S_y)).
bool cholesky_downdate_whitened(Matrix9d& S, const Vector9d& p, const Vector9d& S_p);

}  // namespace magcal
