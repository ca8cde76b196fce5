// ftcal-echo-stage: a minimal stage built on services/common, for the integration tests. It
// reads ft_batch_t on ECHO_IN and publishes each valid one on ECHO_OUT with every record's
// wrench doubled and receipt_utime set to the bus time; every second of bus time it publishes on
// ECHO_TICK an experiment_marker_t whose note is the number of messages echoed so far. Runs live
// or over a log.
#include <cmath>
#include <set>

#include "common/service.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/ft_batch_t.hpp"

int main(int argc, char** argv) {
  ftcal::ServiceApp app({"ftcal-echo-stage",
                         "Test stage: reads ft_batch_t on ECHO_IN; publishes it on ECHO_OUT "
                         "with every record's wrench doubled, and experiment_marker_t on "
                         "ECHO_TICK every second (note: number echoed). Refuses unknown legs "
                         "and NaNs.",
                         /*replayable=*/true});
  if (auto rc = app.Init(argc, argv)) return *rc;
  const std::set<std::string> legs = {"HL", "ML", "FL", "HR", "MR", "FR"};
  int64_t& echoed = app.stats().Counter("echoed");
  app.bus().Subscribe<ftcal::ft_batch_t>(
      "ECHO_IN", [&](const ftcal::MessageInfo& info, const ftcal::ft_batch_t& in) {
        if (legs.count(in.leg) == 0) {
          throw ftcal::BadInput("unknown leg on " + info.channel, "leg '" + in.leg + "'");
        }
        for (const auto& record : in.wrench) {
          for (double w : record) {
            if (!std::isfinite(w)) throw ftcal::BadInput("non-finite wrench", "leg " + in.leg);
          }
        }
        for (int64_t status : in.status) {
          if (status == 666) throw std::runtime_error("handler failure requested by status 666");
        }
        ftcal::ft_batch_t out = in;
        out.receipt_utime = app.bus().NowUtime();
        for (auto& record : out.wrench) {
          for (double& w : record) w *= 2;
        }
        app.bus().Publish("ECHO_OUT", out);
        ++echoed;
      });
  app.AddPeriodic(1.0, [&] {
    ftcal::experiment_marker_t tick{};
    tick.utime = app.bus().NowUtime();
    tick.session_id = "echo";
    tick.note = std::to_string(echoed);
    app.bus().Publish("ECHO_TICK", tick);
  });
  return app.Run();
}
