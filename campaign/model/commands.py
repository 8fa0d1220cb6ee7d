"""`campaign model ...`: inspect the robot model."""

from __future__ import annotations


def register(sub):
    p = sub.add_parser("model", help="inspect the robot model (base parameters, chain)")
    msub = p.add_subparsers(dest="model_command", metavar="WHAT", required=True)
    b = msub.add_parser("base-params", help="print the identifiable base parameters like the paper's Table 3")
    b.add_argument("--robot", default="comau_racer5_080",
                   help="robot: a name under robot_models/, a URDF or a robot.yaml (default: %(default)s)")
    b.add_argument("--tool-frame", default=None, metavar="LINK", help="tool frame (default: robot.yaml's, or the "
                                                                      "chain's last link)")
    b.add_argument("--base-frame", default=None, metavar="LINK", help="base frame (default: the URDF's root)")
    b.add_argument("--position-only", action="store_true", help="position measurements only (no orientation)")
    b.add_argument("--poses", type=int, default=200, help="random poses in the regressor (default: %(default)s)")
    b.set_defaults(func=_base_params)
    c = msub.add_parser("chain", help="print the chain: its transforms, joints and error parameters")
    c.add_argument("--robot", default="comau_racer5_080", help="robot: name, URDF or robot.yaml")
    c.add_argument("--tool-frame", default=None, metavar="LINK")
    c.add_argument("--base-frame", default=None, metavar="LINK")
    c.set_defaults(func=_chain)
    r = sub.add_parser("robots", help="list the robot names --robot accepts (embedded, and example-robot-data's "
                                      "arms when that package is installed)")
    r.set_defaults(func=_robots)


def _robots(args):
    from campaign.model.catalog import known_robots

    rows = known_robots()
    print(f"{'name':<18} {'tool frame':<14} {'base frame':<15} {'source':<19} description")
    for known, path in rows:
        where = known.source if path is not None else f"{known.source} (not installed)"
        print(f"{known.name:<18} {known.tool_frame or '(robot.yaml)' if known.source == 'embedded' else known.tool_frame or '-':<14} "
              f"{known.base_frame or '(URDF root)':<15} {where:<19} {known.description}")
    if any(p is None for _, p in rows):
        print("(pip install example-robot-data for the robots marked not installed)")
    print("any other robot: --robot PATH/robot.urdf --tool-frame LINK, or a robot.yaml (docs/robot_yaml.md)")
    return 0


def _base_params(args):
    from campaign.model.base_params import base_parameters
    from campaign.model.robot import RobotModel

    from campaign.config import check_int

    robot = RobotModel.load(args.robot, tool_frame=args.tool_frame, base_frame=args.base_frame)
    rows = 3 if args.position_only else 6  # regressor rows per pose
    check_int(args.poses, "--poses", low=-(-robot.n_params // rows))  # at least as many rows as parameters
    print(base_parameters(robot, position_only=args.position_only, n_poses=args.poses).table())
    return 0


def _chain(args):
    from campaign.model.robot import RobotModel

    robot = RobotModel.load(args.robot, tool_frame=args.tool_frame, base_frame=args.base_frame)
    print(robot.describe())
    print("error parameters: " + ", ".join(robot.param_names))
    return 0
