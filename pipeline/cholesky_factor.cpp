#include "pipeline/cholesky_factor.hpp"

#include <cmath>

namespace magcal {

bool cholesky_downdate_whitened(Matrix9d& S, const Vector9d& p) {
  return cholesky_downdate_whitened(S, p, lower_triangular_times(S, p));
}

bool cholesky_downdate_whitened(Matrix9d& S, const Vector9d& p, const Vector9d& S_p) {
  // S' = S M with M M^T = I - p p^T lower triangular, in closed form (delta_0 = 1,
  // delta_k = 1 - sum_{j<=k} p_j^2): M_kk = sqrt(delta_k / delta_{k-1}),
  // M_ik = -p_i p_k / sqrt(delta_k delta_{k-1}) (i > k). The square roots and divisions of
  // different columns are independent (no serial chain as in the textbook downdate); column k of
  // S' is a_k S_k - b_k sum_{j>k} p_j S_j, that sum is S p less the columns done. Column k
  // needs only delta_k, so it starts while the later deltas are still being summed.
  double delta = 1.0;
  for (int k = 0; k < 9; ++k) delta -= p(k) * p(k);
  if (!(delta > 0.0)) return false;
  const Vector9d p_local = p;  // p could alias S
  Vector9d rest = S_p;         // sum_{j>=k} p_j S_j before column k (rows >= k are read)
  double delta_prev = 1.0;
  for_each_column<9>([&](auto column) {
    constexpr int k = decltype(column)::value;
    const double delta_k = delta_prev - p_local(k) * p_local(k);
    const double inv = 1.0 / std::sqrt(delta_k * delta_prev);
    const double a = delta_k * inv;     // sqrt(delta_k / delta_{k-1})
    const double b = p_local(k) * inv;  // p_k / sqrt(delta_k delta_{k-1})
    delta_prev = delta_k;
    // S is lower triangular: column k is zero above row k.
    for (int i = k; i < 9; ++i) {
      const double s_ik = S(i, k);
      rest(i) -= p_local(k) * s_ik;
      S(i, k) = a * s_ik - b * rest(i);
    }
  });
  return true;
}

}  // namespace magcal
