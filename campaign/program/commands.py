"""`campaign program RUN --format F [--out FILE] [--speed FRACTION] [--trigger-output N]`."""

from __future__ import annotations

#: the formats `campaign program` writes (campaign.program.generate.FORMATS), for --help without numpy
FORMAT_NAMES = ("urscript", "krl", "rapid", "fanuc-ls", "pdl2", "ros2-trajectory", "csv")


def register(sub):
    p = sub.add_parser(
        "program", help="the planned campaign as a robot program (URScript, KRL, RAPID, FANUC LS, PDL2, ROS 2, CSV)",
        description="Write the planned campaign of RUN (its tour with the via poses, validation poses, repeats and "
                    "drift checks, in the order `campaign run` visits them) as a program for the robot's controller, "
                    "in its joint convention (robot.yaml's controller:) and units, with a dwell at each stop long "
                    "enough to settle and measure every reflector; and RUN/program/stops.csv "
                    "(stop,pose_id,kind,dwell_s,q1..qN, the model's convention), what `campaign import --stream` "
                    "matches a tracker's log to. docs/programs.md.")
    p.add_argument("run", metavar="RUN", help="run folder with plan/poses.csv (from `campaign plan`)")
    p.add_argument("--format", required=True, metavar="F",
                   help=f"the controller's language: {', '.join(FORMAT_NAMES)}")
    p.add_argument("--out", metavar="FILE", default=None,
                   help="the program's file (default: RUN/program/<name>.<ext>; further parts beside it)")
    p.add_argument("--speed", type=float, default=1.0, metavar="FRACTION",
                   help="joint speed and acceleration as a fraction of the robot's limits (default: 1)")
    p.add_argument("--trigger-output", type=int, default=None, metavar="N",
                   help="pulse digital output N at each measured stop (a tracker measuring on a trigger)")
    p.set_defaults(func=_program)


def _program(args):
    from campaign.program.generate import build_program

    res = build_program(args.run, args.format, out=args.out, speed=args.speed, trigger_output=args.trigger_output)
    names = ", ".join(str(f) for f in res.files)
    print(f"wrote {names} ({res.n_stops} stops, {res.n_measured} measured, ~{res.duration_s / 3600:.2f} h) "
          f"and {res.stops_csv}")
    return 0
