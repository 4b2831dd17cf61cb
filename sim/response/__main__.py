"""``python -m sim.response fly|fit|replay``: fly the identification sequence on an autopilot, fit
the recorded runs and compare them, or read recorded policy flights back (see the package doc)."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
from pathlib import Path

from runtime.state import VehicleError

from sim.dynamics import PX4_SIH_V1_16

from .flight import ENDINGS, fly_sequence
from .identify import compare_table, identify
from .replay import REFERENCES, FlightRecordError, estimate_error, load_flights, replay_error


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim.response", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    fly = sub.add_parser("fly", help="fly the identification sequence and write the run's JSON")
    fly.add_argument("--url", default="udpin://127.0.0.1:14540", help="the autopilot's MAVSDK URL (default PX4 SITL's offboard link)")
    fly.add_argument("--ending", choices=ENDINGS, default="brake", help="how the flight ends (default brake)")
    fly.add_argument("--takeoff-alt-m", type=float, default=2.5, help="take-off height above home (m)")
    fly.add_argument("-o", "--out", type=Path, required=True, help="the run's JSON")
    fit = sub.add_parser("fit", help="identify each run's response and print them side by side")
    fit.add_argument("runs", type=Path, nargs="+", metavar="NAME=RUN.json", help="runs written by `fly`, each named")
    fit.add_argument("-o", "--out", type=Path, help="also write the identified parameters as JSON")
    replay = sub.add_parser("replay", help="recorded `cmnav sitl --autopilot` flights: the autopilot's estimate against the "
                            "ground truth, and sim.dynamics.PX4_SIH_V1_16 replayed on the commands sent")  # fmt: skip
    replay.add_argument("runs", type=Path, nargs="+", metavar="DIR", help="run directories, or campaign directories (their runs/*)")
    replay.add_argument("--horizon-s", type=float, default=1.0, help="how far each replayed window flies (default 1 s)")
    replay.add_argument("-o", "--out", type=Path, help="also write the result as JSON")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.command == "fly":
        try:
            run = asyncio.run(fly_sequence(args.url, args.ending, args.takeoff_alt_m))
        except VehicleError as err:
            print(f"error: {err}", file=sys.stderr)
            return 1
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(run))
        print(f"run written to {args.out}: {len(run['samples']['t_s'])} samples, end {run['end']}")
        return 0
    if args.command == "replay":
        return _replay(args)
    identified = {}
    for named in args.runs:
        name, sep, path = str(named).partition("=")
        if not sep:
            name, path = Path(named).stem, str(named)
        try:
            identified[name] = identify(json.loads(Path(path).read_text()))
        except (OSError, ValueError, KeyError) as err:
            print(f"error: cannot identify {path}: {err}", file=sys.stderr)
            return 2
    print(compare_table(identified))
    if args.out is not None:
        args.out.write_text(json.dumps(identified, indent=2))
    return 0


def _replay(args: argparse.Namespace) -> int:
    try:
        flights = load_flights(args.runs)
        result = {"estimate_error": estimate_error(flights), "corrected_estimate_error": estimate_error(flights, corrected=True),
                  "replay": {ref: replay_error(flights, PX4_SIH_V1_16, ref, args.horizon_s) for ref in REFERENCES}}  # fmt: skip
    except (FlightRecordError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for key, whose in (("estimate_error", "the autopilot's estimate"), ("corrected_estimate_error", "the runtime's corrected estimate")):
        err = result[key]
        print(f"{err['flights']} flights, {err['samples']} estimates in offboard; {whose} - truth (x, y, z):")
        for stat, label in (("bias_sd", "per-flight mean, sd over flights"), ("within_flight_sd", "about it, within a flight (sd)")):
            print(f"  {label}: position {err[stat]['position_m']} m, velocity {err[stat]['velocity_m_s']} m/s")
        for lag, values in err["autocorrelation"].items():
            print(f"  autocorrelation at {lag} s: position {values['position_m']}, velocity {values['velocity_m_s']}")
    for ref, rep in result["replay"].items():
        for at_s, e in rep["at_s"].items():
            print(f"PX4_SIH_V1_16 replayed against the {ref}, {at_s} s ahead ({rep['windows']} windows): "
                  f"RMS forward/left/up {e['rms'][:3]} m/s, heading {e['rms'][3]} rad")  # fmt: skip
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
