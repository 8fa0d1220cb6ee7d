"""`campaign model ...`: inspect the robot model."""

from __future__ import annotations


def register(sub):
    p = sub.add_parser("model", help="inspect the robot model (base parameters, chain)")
    msub = p.add_subparsers(dest="model_command", metavar="WHAT", required=True)
    b = msub.add_parser("base-params", help="print the identifiable base parameters like the paper's Table 3")
    b.add_argument("--robot", default="comau_racer5_080", help="robot folder name or path (default: %(default)s)")
    b.add_argument("--position-only", action="store_true", help="position measurements only (no orientation)")
    b.add_argument("--poses", type=int, default=200, help="random poses in the regressor (default: %(default)s)")
    b.set_defaults(func=_base_params)


def _base_params(args):
    from campaign.model.base_params import base_parameters
    from campaign.model.robot import RobotModel

    robot = RobotModel.load(args.robot)
    print(base_parameters(robot, position_only=args.position_only, n_poses=args.poses).table())
    return 0
