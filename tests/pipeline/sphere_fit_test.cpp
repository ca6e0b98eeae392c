// Algebraic sphere fit (pipeline/sphere_fit.hpp): truth recovery on simulated constant-field
// data, noise consistency, and the off-nominal cases.
#include "pipeline/sphere_fit.hpp"

#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include <Eigen/Core>
#include <catch2/catch.hpp>

using namespace magcal;

namespace {

// Samples c + r u_k + noise, u_k uniform on the sphere (or on a cap/plane when restricted).
std::vector<Eigen::Vector3d> sphere_samples(const Eigen::Vector3d& c, double r, double sigma, int n,
                                            unsigned seed, bool planar = false) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  std::vector<Eigen::Vector3d> out;
  for (int k = 0; k < n; ++k) {
    Eigen::Vector3d u(g(rng), g(rng), planar ? 0.0 : g(rng));
    u.normalize();
    out.push_back(c + r * u + sigma * Eigen::Vector3d(g(rng), g(rng), g(rng)));
  }
  return out;
}

}  // namespace

TEST_CASE("sphere fit recovers centre and radius of noise-free data exactly", "[sphere]") {
  const Eigen::Vector3d c(-310.0, -110.0, 390.0);
  const double r = 44520.0;
  const auto b = sphere_samples(c, r, 0.0, 200, 1);
  const SphereFitResult f = fit_sphere(b);
  REQUIRE(f.ok());
  constexpr double kExactTol_nT = 1e-6;
  CHECK((f.center_nT - c).norm() < kExactTol_nT);
  CHECK(std::abs(f.radius_nT - r) < kExactTol_nT);
  CHECK(f.residual_rms_nT < kExactTol_nT);
  CHECK(f.n_samples == 200);
}

TEST_CASE("sphere fit with noise: errors consistent with the noise level", "[sphere]") {
  const Eigen::Vector3d c(5000.0, -3000.0, 800.0);
  const double r = 30000.0, sigma = 300.0;
  const int n = 5000;
  const auto b = sphere_samples(c, r, sigma, n, 7);
  const SphereFitResult f = fit_sphere(b);
  REQUIRE(f.ok());
  // Isotropic coverage: each centre coordinate has sd ~ sigma sqrt(3/n), the radius ~
  // sigma/sqrt(n); the residual rms is the radial noise, sigma.
  const double sd_c = sigma * std::sqrt(3.0 / n), sd_r = sigma / std::sqrt(double(n));
  constexpr double kSigmas = 5.0;
  CHECK((f.center_nT - c).cwiseAbs().maxCoeff() < kSigmas * sd_c);
  CHECK(std::abs(f.radius_nT - r) < kSigmas * sd_r + sigma * sigma / r);  // + algebraic bias
  CHECK(f.residual_rms_nT == Approx(sigma).epsilon(0.05));
}

TEST_CASE("sphere fit off-nominal: too few, NaN, planar, invalid options", "[sphere]") {
  const Eigen::Vector3d c(1.0, 2.0, 3.0);
  SECTION("too few samples") {
    const SphereFitResult f = fit_sphere(sphere_samples(c, 100.0, 0.0, 5, 2));
    CHECK(f.status == SphereFitStatus::kTooFewSamples);
    CHECK_FALSE(f.message.empty());
  }
  SECTION("NaN sample") {
    auto b = sphere_samples(c, 100.0, 0.0, 50, 3);
    b[10](1) = std::numeric_limits<double>::quiet_NaN();
    CHECK(fit_sphere(b).status == SphereFitStatus::kInvalidInput);
  }
  SECTION("samples on a great circle (plane): centre not determined") {
    const SphereFitResult f = fit_sphere(sphere_samples(c, 100.0, 0.0, 100, 4, true));
    CHECK(f.status == SphereFitStatus::kDegenerate);
  }
  SECTION("all samples identical") {
    const std::vector<Eigen::Vector3d> b(50, Eigen::Vector3d(1.0, 1.0, 1.0));
    CHECK(fit_sphere(b).status == SphereFitStatus::kDegenerate);
  }
  SECTION("invalid options") {
    SphereFitOptions o;
    o.min_samples = 3;
    CHECK_FALSE(o.validate().empty());
    CHECK(fit_sphere(sphere_samples(c, 100.0, 0.0, 50, 5), o).status ==
          SphereFitStatus::kInvalidInput);
  }
}
