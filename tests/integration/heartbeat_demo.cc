// ftcal-heartbeat-demo: a process built on services/common with something to count, for the
// integration tests: it publishes a DEMO_TICK message every 100 ms, subscribes to the same
// channel (LCM multicast loops back), and counts ticks.
#include "common/service.h"
#include "ftcal/experiment_marker_t.hpp"

int main(int argc, char** argv) {
  ftcal::ServiceApp app({"ftcal-heartbeat-demo",
                         "Test program: publishes experiment_marker_t on DEMO_TICK every 100 ms, "
                         "reads DEMO_TICK back, counts both (counters ticks, heard).",
                         /*replayable=*/false});
  if (auto rc = app.Init(argc, argv)) return *rc;
  int64_t& ticks = app.stats().Counter("ticks");
  int64_t& heard = app.stats().Counter("heard");
  app.bus().Subscribe<ftcal::experiment_marker_t>(
      "DEMO_TICK",
      [&heard](const ftcal::MessageInfo&, const ftcal::experiment_marker_t&) { ++heard; });
  app.AddPeriodic(0.1, [&] {
    ftcal::experiment_marker_t msg{};
    msg.utime = app.bus().NowUtime();
    msg.session_id = "demo";
    msg.phase = ftcal::experiment_marker_t::IDLE;
    msg.note = std::to_string(++ticks);
    app.bus().Publish("DEMO_TICK", msg);
  });
  return app.Run();
}
