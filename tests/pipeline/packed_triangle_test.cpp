// Packed symmetric storage: exact round trips and the index.
#include "pipeline/packed_triangle.hpp"

#include <cmath>
#include <random>

#include <catch2/catch.hpp>

using namespace magcal;

namespace {

template <int N>
Eigen::Matrix<double, N, N> random_matrix(uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> n(0.0, 1.0);
  Eigen::Matrix<double, N, N> M;
  for (int j = 0; j < N; ++j) {
    for (int i = 0; i < N; ++i) M(i, j) = n(rng) * std::pow(10.0, i - j);  // mixed scales
  }
  return M;
}

}  // namespace

TEST_CASE("a symmetric matrix packs and unpacks exactly") {
  const Eigen::Matrix<double, 9, 9> A = random_matrix<9>(1);
  const Eigen::Matrix<double, 9, 9> sym = A + A.transpose();
  const PackedTriangle<9> p = packed_upper<9>(sym);
  CHECK(symmetric_from_packed<9>(p) == sym);
  for (int i = 0; i < 9; ++i) {
    for (int j = i; j < 9; ++j) CHECK(p(packed_index<9>(i, j)) == sym(i, j));
  }
  const Eigen::Matrix<double, 11, 11> B = random_matrix<11>(2);
  const Eigen::Matrix<double, 11, 11> sym11 = B + B.transpose();
  CHECK(symmetric_from_packed<11>(packed_upper<11>(sym11)) == sym11);
}
