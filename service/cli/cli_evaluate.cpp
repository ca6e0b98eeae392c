// `magcal evaluate --scenario paper|pure|FILE.toml --runs N [--seed S] [--json]`: the paper's
// Monte-Carlo protocol (service/analysis/evaluation.hpp) and its Table 8 side by side with ours.
// Exit: 0 table printed; 1 bad arguments / unknown scenario / bad scenario file.
#include <iostream>

#include "service/analysis/evaluation.hpp"
#include "service/cli/cli_commands.hpp"
#include "service/io/scenario_file.hpp"

namespace magcal::cli {

int run_evaluate(const EvaluateArgs& args) {
  EvaluationOptions opt;
  if (auto preset = scenario_preset(args.scenario)) {
    opt.scenario = *preset;
  } else if (args.scenario.size() > 5 &&
             args.scenario.compare(args.scenario.size() - 5, 5, ".toml") == 0) {
    const ScenarioLoadResult load = load_scenario_file(args.scenario);
    if (!load.ok()) {
      std::cerr << "magcal evaluate: " << load.error << "\n";
      return kExitUsage;
    }
    opt.scenario = *load.scenario;
  } else {
    std::cerr << "magcal evaluate: unknown scenario '" << args.scenario
              << "' (presets: paper, pure, tumbling; or FILE.toml)\n";
    return kExitUsage;
  }
  opt.runs = args.runs;
  opt.seed = args.seed;
  if (std::string err = opt.validate(); !err.empty()) {
    std::cerr << "magcal evaluate: " << err << "\n";
    return kExitUsage;
  }
  const EvaluationReport report = run_evaluation(opt);
  if (args.json) {
    std::cout << evaluation_to_json(report).dump(2) << "\n";
  } else {
    std::cout << format_evaluation_table(report);
  }
  return kExitOk;
}

}  // namespace magcal::cli
