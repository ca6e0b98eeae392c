// `magcal refit --db FILE|URI --sat ID [--config FILE.toml] [--json]`: the daemon's refit
// (refit_runner.hpp) run now, in this process, on the stored window ending at the spacecraft's
// newest sample. Safe while magcald runs (own connection; SQLite WAL + busy timeout, or
// PostgreSQL). Writes the result to the history and a 'manual' job row, prints the result. The
// config supplies the window length, min_samples, sigma and the gates (the daemon's defaults
// without one). Exit: 0 a result was computed and stored (accepted or rejected), 2 missing
// database, no or too few samples (refused: nothing written), failed fit, database error; 1 bad
// config.
#include <algorithm>
#include <filesystem>
#include <iostream>

#include <fmt/format.h>

#include "pipeline/time_utc.hpp"
#include "service/cli/cli_commands.hpp"
#include "service/config/daemon_config.hpp"
#include "service/io/result_json.hpp"
#include "service/refit/refit_runner.hpp"

namespace magcal::cli {

int run_refit(const RefitArgs& args) {
  auto load = load_daemon_config(args.config);
  if (!load.ok()) {
    std::cerr << "magcal refit: " << load.error << "\n";
    return kExitUsage;
  }
  const DaemonConfig& config = load.config;
  const std::string db_name = storage::database_name(args.db);
  // An open that would create a missing database must not (a refit of nothing).
  if (storage::capabilities_of(args.db).open_creates_missing && !std::filesystem::exists(args.db)) {
    std::cerr << "magcal refit: database " << db_name << " does not exist\n";
    return kExitData;
  }
  RefitOutcome out;
  try {
    const auto db = storage::open_database(args.db);
    RefitRunner runner(config, *db);
    // A refit that would only be skipped is refused here, before its job row is written.
    if (const std::string why = runner.skip_reason(args.sat, std::nullopt); !why.empty()) {
      // An unknown id (a typo?) is answered with the ones stored.
      const auto all = runner.spacecraft();
      std::string stored;
      for (size_t k = 0; k < all.size() && k < 10; ++k) stored += (k ? ", " : "") + all[k];
      if (all.size() > 10) stored += ", ... (" + std::to_string(all.size()) + " in all)";
      const bool known = std::find(all.begin(), all.end(), args.sat) != all.end();
      std::cerr << "magcal refit: " << why << " in " << db_name
                << (known         ? ""
                    : all.empty() ? " (no spacecraft stored)"
                                  : " (spacecraft stored: " + stored + ")")
                << "; nothing written\n";
      return kExitData;
    }
    out = runner.run(args.sat, std::nullopt, storage::RefitTrigger::kManual, now_utime());
  } catch (const storage::StorageError& e) {
    std::cerr << "magcal refit: database " << db_name << ": " << e.what() << "\n";
    return kExitData;
  }
  if (out.kind != RefitOutcome::Kind::kComputed) {
    std::cerr << "magcal refit: " << args.sat << ": " << out.message << "\n";
    return kExitData;
  }
  const CalibrationResult& r = out.result;
  if (args.json) {
    auto j = calibration_result_to_json(r);
    j["sat_id"] = args.sat;
    j["time"] = format_iso8601_utc(r.utime);
    j["window_start"] = format_iso8601_utc(r.window_start_utime);
    j["window_end"] = format_iso8601_utc(r.window_end_utime);
    j["calibration_id"] = out.calibration_id;
    j["job_id"] = out.job_id;
    std::cout << j.dump(2) << "\n";
  } else {
    const Eigen::Vector3d b = r.parameters.bias_nT;
    const Eigen::Vector3d s = r.bias_sigma_nT();
    const Eigen::Matrix3d& D = r.parameters.D;
    std::cout << fmt::format(
        "refit {} ({}), window {} .. {}, {} samples\n"
        "  status {}, verdict {}{}\n"
        "  bias_nT  [{:.2f}, {:.2f}, {:.2f}] +- [{:.2f}, {:.2f}, {:.2f}]\n"
        "  D        [[{:.5f}, {:.5f}, {:.5f}], [{:.5f}, {:.5f}], [{:.5f}]] (upper)\n"
        "  residual {:.2f} nT rms, {} iterations{}\n",
        args.sat, r.method, format_iso8601_utc(r.window_start_utime),
        format_iso8601_utc(r.window_end_utime), r.n_samples, to_string(r.status),
        r.accepted ? "accepted" : "rejected",
        r.rejection_reasons.empty()
            ? ""
            : " (" + fmt::format("{}", fmt::join(r.rejection_reasons, "; ")) + ")",
        b.x(), b.y(), b.z(), s.x(), s.y(), s.z(), D(0, 0), D(0, 1), D(0, 2), D(1, 1), D(1, 2),
        D(2, 2), r.residual_rms_nT, r.iterations, r.has_alignment ? ", alignment estimated" : "");
    if (r.has_temperature_model) {  // bias_nT is then the bias at T0
      const Eigen::Vector3d& k = r.temperature_coefficient_nT_per_C;
      const Eigen::Vector3d ks = r.temperature_coefficient_sigma_nT_per_C();
      std::cout << fmt::format(
          "  bias at T0 = {:.2f} degC; k_T [{:.3f}, {:.3f}, {:.3f}] +- [{:.3f}, {:.3f}, {:.3f}] "
          "nT/degC\n",
          r.reference_temperature_C, k.x(), k.y(), k.z(), ks.x(), ks.y(), ks.z());
    }
    if (r.has_bias_rate) {  // bias_nT is then the bias at the window's end
      const Eigen::Vector3d& rate = r.bias_rate_nT_per_h;
      const Eigen::Vector3d rs = r.bias_rate_sigma_nT_per_h();
      std::cout << fmt::format(
          "  bias at the window's end; bias rate [{:.3f}, {:.3f}, {:.3f}] +- [{:.3f}, {:.3f}, "
          "{:.3f}] nT/h\n",
          rate.x(), rate.y(), rate.z(), rs.x(), rs.y(), rs.z());
    }
  }
  return (r.status == CalibrationStatus::kOk || r.status == CalibrationStatus::kRejected)
             ? kExitOk
             : kExitData;
}

}  // namespace magcal::cli
