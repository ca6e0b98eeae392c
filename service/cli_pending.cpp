// SCAFFOLDING for this session only: subcommands whose cli_<name>.cpp is not written yet.
// Whoever implements run_X deletes it here. This file must be gone before the session ends.
#include <iostream>

#include "service/cli_commands.hpp"

namespace magcal::cli {
namespace {
int pending(const char* name) {
  std::cerr << "magcal " << name << ": not built yet\n";
  return kExitUsage;
}
}  // namespace
int run_field(const FieldArgs&) { return pending("field"); }
int run_sim(const SimArgs&) { return pending("sim"); }
int run_fit(const FitArgs&) { return pending("fit"); }
int run_evaluate(const EvaluateArgs&) { return pending("evaluate"); }
int run_refit(const RefitArgs&) { return pending("refit"); }
int run_history(const HistoryArgs&) { return pending("history"); }
int run_status(const StatusArgs&) { return pending("status"); }
}  // namespace magcal::cli
