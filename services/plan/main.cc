// ftcal-plan --predict: the sigma every parameter class of an experiment plan will have, and
// the plan's robot time, before the plan runs (plan_predict.h).
#include <cstdio>
#include <exception>
#include <string>

#include <CLI/CLI.hpp>

#include "common/exit_codes.h"
#include "common/user_errors.h"
#include "ftcal/config.h"
#include "plan/plan_predict.h"

int main(int argc, char** argv) try {
  CLI::App cli(
      "ftcal-plan: predicts, from the model's information matrix at the nominal parameters and "
      "the config's planner noise, each parameter class's sigma for an experiment plan of the "
      "config (median and worst parameter; 'reported' is what the calibrator's covariance would "
      "say), and the plan's robot time.\n" +
      std::string(ftcal::ExitCodeTable()));
  std::string config_path, plan_name;
  bool predict = false;
  cli.add_option("--config", config_path, "config file (protobuf text)")->required();
  cli.add_flag("--predict", predict, "predict the sigma of --plan")->required();
  cli.add_option("--plan", plan_name, "experiment plan by name (default: the config's first)");
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e) == 0 ? ftcal::kExitDone : ftcal::kExitUsage;
  }
  ftcal::config::Config config;
  try {
    config = ftcal::LoadConfigFile(config_path);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "ftcal-plan: %s\n", ftcal::UserText(e, "reading the config").c_str());
    return ftcal::kExitConfig;
  }
  try {
    const auto report = ftcal::plan::PredictConfigPlan(config, plan_name);
    std::fputs(ftcal::plan::FormatReport(report).c_str(), stdout);
    return ftcal::kExitDone;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "ftcal-plan: %s\n", ftcal::UserText(e, "predicting the plan").c_str());
    return ftcal::IsInternalError(e) ? ftcal::kExitInternal : ftcal::kExitConfig;
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-plan");
}
