#!/usr/bin/env python3
"""Keep what PX4 estimated and what SIH's ground truth said, in offboard, for a few recorded
flights of `cmnav sitl --autopilot` (scripts/px4-campaign.sh's run directories): the fixture
that tests runtime.tracking.VelocityBias on PX4's own estimates.

    python scripts/px4-velocity-fixture.py RUN_DIR... -o tests/runtime/fixtures/px4_v1_16_velocity_bias.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim.response.replay import load_flight  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (trace.json + flight.mcap)")
    parser.add_argument("-o", "--out", type=Path, required=True)
    args = parser.parse_args()
    flights = []
    for run in args.runs:
        flight = load_flight(run)
        est = flight.estimate
        _, truth_vel, _ = flight.truth.at(est.t_s)

        def rounded(a, digits=4):
            return [[round(float(v), digits) for v in row] for row in a]

        flights.append({
            "name": flight.name,
            "t_s": [round(float(t - est.t_s[0]), 4) for t in est.t_s],
            "pos_enu_m": rounded(est.pos_enu_m),
            "vel_enu_m_s": rounded(est.vel_enu_m_s),
            "truth_vel_enu_m_s": rounded(truth_vel),
        })
    record = {
        "what": "PX4 v1.16.0 SIH (airframe 10040) in offboard: the runtime's ODOMETRY estimate (room axes, ENU; t_s from the "
                "first, host receive times) and SIH's ground-truth velocity at those times (HIL_STATE_QUATERNION, interpolated)",
        "command": "python scripts/px4-velocity-fixture.py " + " ".join(str(r) for r in args.runs),
        "flights": flights,
    }
    args.out.write_text(json.dumps(record, separators=(",", ":")) + "\n")
    print(f"{args.out}: {len(flights)} flights, {sum(len(f['t_s']) for f in flights)} estimates")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
