"""`campaign plan [--config FILE] [--run DIR] [--grid-scale S]`."""

from __future__ import annotations

import sys


def register(sub):
    p = sub.add_parser("plan", help="plan a collision-free list of measurement poses (embedded defaults without a config)")
    p.add_argument("--config", metavar="FILE", default=None, help="campaign.yaml (default: the embedded one)")
    p.add_argument("--run", metavar="DIR", default="runs/default", help="run folder (default: %(default)s)")
    p.add_argument("--grid-scale", type=float, default=1.0,
                   help="scale the cells per axis for a coarser (<1) or finer grid (default: 1 = 1,428,000 candidates)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_plan)


def _plan(args):
    from campaign.errors import ConfigError
    from campaign.plan.pipeline import plan_campaign

    if not args.grid_scale > 0:
        raise ConfigError(f"--grid-scale must be positive, got {args.grid_scale}")
    s = plan_campaign(args.config, args.run, grid_scale=args.grid_scale, progress=not args.quiet and sys.stderr.isatty())
    rm = s["removed_by_filter"]
    est = s["estimated_campaign"]
    print(f"candidates {s['candidates']:,} (grid {' x '.join(map(str, s['grid_cells']))})")
    for name in s["filter_order"]:
        print(f"  removed by {name:<22} {rm[name]:>10,}")
    print(f"suitable poses {s['suitable']:,} ({100 * s['suitable_fraction']:.2f} %): "
          f"{s['groups']['front_of_wall']:,} in front of the wall, {s['groups']['behind_wall']:,} behind")
    t = s["tour"]
    print(f"tour: {t['poses']:,} poses, {t['via_poses']} via poses, {t['dropped']} dropped; motion {t['motion_time_s'] / 3600:.2f} h")
    print(f"estimated campaign {est['total_days']:.2f} days ({est['seconds_per_pose']:.1f} s a pose) "
          f"vs the paper's {est['paper']['duration_days']:.1f} days for {est['paper']['poses']:,} poses "
          f"({est['paper']['seconds_per_pose']:.1f} s a pose)")
    print(f"written: {args.run}/plan/poses.csv, summary.json, tour.png ({s['timing_s']['total']:.1f} s)")
    return 0
