"""`campaign plan [--config FILE] [--run DIR] [--robot NAME|URDF|robot.yaml] [--tool-frame LINK] [--base-frame LINK]
[--grid-scale S] [--select N | --budget HOURS | --target-mm X | --all] [--for-effects a,b]`: by default the
short campaign for the physical model (the 120 most informative suitable poses, validation poses and
repeats); ``--all`` every suitable pose (the long campaign)."""

from __future__ import annotations

import sys


def register(sub):
    from campaign.plan.defaults import DEFAULT_SELECT, REPEAT_POSES, REPEAT_TIMES

    p = sub.add_parser("plan", help="plan a collision-free list of measurement poses (embedded defaults without a "
                                    "config): by default a short campaign for the physical model, --all every "
                                    "suitable pose")
    p.add_argument("--config", metavar="FILE", default=None,
                   help="campaign.yaml (default: the run's own when it has one, else the embedded one)")
    p.add_argument("--run", metavar="DIR", default="runs/default",
                   help="run folder (default: %(default)s); a run holding measurements is refused")
    p.add_argument("--robot", metavar="NAME|URDF|robot.yaml", default=None,
                   help="plan for this robot (default: the configuration's; recorded in RUN/campaign.yaml): its URDF's "
                        "collision geometry and joint limits, robot.yaml's reflectors (docs/robot_yaml.md)")
    p.add_argument("--tool-frame", metavar="LINK", default=None, help="the robot's tool frame (default: the robot's)")
    p.add_argument("--base-frame", metavar="LINK", default=None, help="the robot's base frame (default: the URDF's root)")
    p.add_argument("--grid-scale", type=float, default=1.0,
                   help="scale the cells per axis for a coarser (<1) or finer grid (default: 1 = 1,428,000 candidates "
                        "for the default robot, about a million for another: plan.grid_cells in campaign.yaml)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--select", type=int, metavar="N", default=None,
                     help="measure the N suitable poses most informative about the model (D-optimal; default: "
                          f"{DEFAULT_SELECT}, a short campaign for the physical model)")
    how.add_argument("--budget", type=float, metavar="HOURS", default=None,
                     help="the most informative campaign that fits in HOURS (motion, settle, tracker)")
    how.add_argument("--target-mm", type=float, metavar="X", default=None,
                     help="the smallest campaign predicted to bring the model's mean position error to X mm")
    how.add_argument("--all", dest="all_poses", action="store_true",
                     help="measure every suitable pose: the long campaign a neural compensator needs (days)")
    p.add_argument("--for-effects", metavar="A,B", default=None,
                   help="effects whose parameters the selection must teach too (default: those in campaign.yaml)")
    p.add_argument("--criterion", choices=("D", "A", "I"), default=None,
                   help="optimality: D (log det, default), A (trace of the covariance), I (mean position variance)")
    p.add_argument("--validation", type=float, metavar="FRACTION", default=None,
                   help="random validation poses added, as a share of the selected ones (default: 0.2, at least 30)")
    p.add_argument("--repeats", type=int, metavar="N", default=None,
                   help=f"poses measured {REPEAT_TIMES} times back to back (each repeat after the next tour pose) for "
                        f"the noise floor (default: {REPEAT_POSES} with a selection)")
    iso = p.add_argument_group("ISO 9283 (pose accuracy and repeatability test; `campaign iso9283 RUN` evaluates it)")
    iso.add_argument("--iso9283", action="store_true",
                     help="plan the standard's test instead: P1..P5 of the largest suitable cube, visited in cycles")
    iso.add_argument("--cycles", type=int, metavar="N", default=None, help="cycles of the five poses (default: 30)")
    iso.add_argument("--compensate", metavar="CALIBRATED_RUN", default=None,
                     help="correct the test's joint commands with this calibrated run's model (the test after "
                          "calibration)")
    p.add_argument("--choose-among", choices=("reachable", "suitable"), default="reachable",
                   help="reachable (default): choose among the suitable poses that collision-free motions join into "
                        "one tour; suitable: among every suitable pose, choosing again for the poses the tour drops")
    p.set_defaults(func=_plan)


def _plan(args):
    if args.iso9283 or args.cycles is not None or args.compensate is not None:
        return _plan_iso9283(args)
    from campaign.plan.pipeline import plan_campaign

    selection = _selection_options(args)
    s = plan_campaign(args.config, args.run, grid_scale=args.grid_scale, progress=not args.quiet and sys.stderr.isatty(),
                      selection=selection, all_poses=args.all_poses, robot=args.robot, tool_frame=args.tool_frame,
                      base_frame=args.base_frame, choose_among=args.choose_among)
    rm = s["removed_by_filter"]
    est = s["estimated_campaign"]
    print(f"candidates {s['candidates']:,} (grid {' x '.join(map(str, s['grid_cells']))})")
    for name in s["filter_order"]:
        print(f"  removed by {name:<22} {rm[name]:>10,}")
    t = s["tour"]
    if "selection" in s:  # the wall groups are the tour's, not the suitable poses'
        print(f"suitable poses {s['suitable']:,} ({100 * s['suitable_fraction']:.2f} %)")
        if s["campaign"]["mode"] == "default":
            print(f"campaign: {s['campaign']['text']}")
        if "reachable" in s:
            print(reachable_text(s["reachable"]))
        print(selection_text(s["selection"]))
        rep = s["selection"]["replacement"]
        if rep["rounds"] > 1 or rep["why_short"]:
            print(f"replaced {rep['replaced']} chosen poses that no collision-free motion reached, choosing "
                  f"{rep['rounds']} times" + (f"; {s['selection']['chosen'] - s['selection']['selected']} chosen "
                                              f"poses not toured: {rep['why_short']}" if rep["why_short"] else ""))
        print(f"tour: {t['poses']:,} poses ({s['groups']['front_of_wall']:,} in front of the wall, "
              f"{s['groups']['behind_wall']:,} behind), {t['via_poses']} via poses, {t['dropped']} dropped; "
              f"motion {t['motion_time_s'] / 3600:.2f} h")
    else:
        print(f"suitable poses {s['suitable']:,} ({100 * s['suitable_fraction']:.2f} %): "
              f"{s['groups']['front_of_wall']:,} in front of the wall, {s['groups']['behind_wall']:,} behind")
        print(f"campaign: {s['campaign']['text']}")
        print(f"tour: {t['poses']:,} poses, {t['via_poses']} via poses, {t['dropped']} dropped; "
              f"motion {t['motion_time_s'] / 3600:.2f} h")
    if "selection" in s:
        print(f"estimated campaign {est['total_s'] / 3600:.2f} h ({est['seconds_per_pose']:.1f} s a pose) "
              f"vs the paper's {est['paper']['duration_days']:.1f} days for {est['paper']['poses']:,} poses")
    else:
        print(f"estimated campaign {est['total_days']:.2f} days ({est['seconds_per_pose']:.1f} s a pose) "
              f"vs the paper's {est['paper']['duration_days']:.1f} days for {est['paper']['poses']:,} poses "
              f"({est['paper']['seconds_per_pose']:.1f} s a pose)")
    dm = s.get("drift_monitor") or {}
    if dm.get("not_clear_after_pose_ids"):
        print(f"warning: {len(dm['not_clear_after_pose_ids'])} of the drift check's {dm['checks']} returns to the "
              f"reference pose {dm['reference_pose_id']} are not clear by plan.motion_clearance_m (after poses "
              f"{', '.join(map(str, dm['not_clear_after_pose_ids'][:5]))}): the driver skips those checks "
              "(run.drift_check_every in campaign.yaml sets how often it checks; 0: never)")
    extra = ", validation.csv, repeats.csv" if "selection" in s else ""
    print(f"written: {args.run}/plan/poses.csv{extra}, summary.json, tour.png ({s['timing_s']['total']:.1f} s)")
    return 0


def _plan_iso9283(args):
    from campaign.errors import ConfigError
    from campaign.iso9283.plan import DEFAULT_CYCLES, plan_iso9283

    if not args.iso9283:
        raise ConfigError("--cycles and --compensate belong to the ISO 9283 test: give them with --iso9283")
    for flag, value in (("--select", args.select), ("--budget", args.budget), ("--target-mm", args.target_mm),
                        ("--all", args.all_poses or None), ("--for-effects", args.for_effects),
                        ("--validation", args.validation), ("--repeats", args.repeats), ("--criterion", args.criterion)):
        if value is not None:
            raise ConfigError(f"{flag} chooses a calibration campaign; --iso9283 plans the standard's five poses")
    s = plan_iso9283(args.config, args.run, cycles=DEFAULT_CYCLES if args.cycles is None else args.cycles,
                     compensate=args.compensate, grid_scale=args.grid_scale,
                     progress=not args.quiet and sys.stderr.isatty(), robot=args.robot, tool_frame=args.tool_frame,
                     base_frame=args.base_frame)
    iso, t, est = s["iso9283"], s["tour"], s["estimated_campaign"]
    print(f"suitable poses {s['suitable']:,} of {s['candidates']:,} candidates (the cube's centre is one of them)")
    print(f"ISO 9283 cube: edge {1e3 * iso['edge_m']:.0f} mm, centre ({', '.join(f'{1e3 * c:.0f}' for c in iso['centre_m'])}) mm "
          f"in F_I; P1..P5, {iso['cycles']} cycles of P1, P5, P4, P3, P2"
          + (f"; commands compensated with {iso['compensated_with']}" if iso["compensated_with"] else ""))
    print(f"tour: {t['poses']:,} poses, motion {t['motion_time_s'] / 60:.1f} min; estimated {est['total_s'] / 3600:.2f} h")
    if iso.get("outside_domain"):
        print(f"warning: {', '.join(iso['outside_domain'])} outside the calibrated domain of {iso['compensated_with']} "
              "(their corrections are extrapolated; iso9283.json: in_domain, sigma_mm)", file=sys.stderr)
    print(f"written: {args.run}/plan/poses.csv, iso9283.json, summary.json ({s['timing_s']['total']:.1f} s)")
    return 0


def _selection_options(args):
    from campaign.effects.base import parse_effect_list
    from campaign.plan.selection import REPEAT_POSES, SelectionOptions

    if args.all_poses:
        from campaign.errors import ConfigError

        for flag, value in (("--for-effects", args.for_effects), ("--validation", args.validation),
                            ("--repeats", args.repeats), ("--criterion", args.criterion)):
            if value is not None:
                raise ConfigError(f"{flag} chooses poses: --all measures every suitable pose, give one without the other")
        return None
    if args.select is None and args.budget is None and args.target_mm is None:
        if all(v is None for v in (args.for_effects, args.validation, args.repeats, args.criterion)):
            return None  # the default short campaign (plan_campaign)
        from campaign.plan.selection import DEFAULT_SELECT

        args.select = DEFAULT_SELECT  # the default short campaign, with these options
    if args.for_effects is not None:
        effects = parse_effect_list(args.for_effects, "--for-effects")
    else:
        from campaign.run import RunFolder

        effects = RunFolder(args.run, config=args.config).effects
    kw = {}
    if args.validation is not None:
        kw["validation_fraction"] = args.validation
    return SelectionOptions(n=args.select, budget_h=args.budget, target_mm=args.target_mm, effects=effects,
                            criterion=args.criterion or "D",
                            repeat_poses=REPEAT_POSES if args.repeats is None else args.repeats, **kw).check()


def reachable_text(r) -> str:
    """The reachable set in one line: how many suitable poses one tour can visit, and why not the others."""
    why = "; ".join(f"{n:,} beyond {k}" for k, n in r["outside_by_barrier"].items())
    text = (f"reachable: {r['inside']:,} of the {r['suitable']:,} suitable poses joined by collision-free motions"
            + (f" ({r['outside']:,} outside: {why})" if r["outside"] else ""))
    if r["chosen_among"] == "suitable":
        text += f"; chosen among every suitable pose: {r.get('why_suitable', 'as asked')}"
    return text


def selection_text(sel) -> str:
    """What the selection chose and what it predicts, in a few lines."""
    from campaign.plan.selection import sample_text

    p = sel["predicted"]
    what = (f"{sel['select']} poses" if "select" in sel else f"a {sel['budget_h']:g} h budget" if "budget_h" in sel
            else f"a target of {sel['target_mm']:g} mm")
    eff = f" + {', '.join(sel['effects'])}" if sel["effects"] else ""
    return "\n".join([
        f"selection ({sel['criterion']}-optimal for {what}; {sel['n_unknowns']} unknowns: geometry{eff}): "
        + (f"{sel['selected']} poses chosen, " if sel.get("chosen", sel["selected"]) == sel["selected"] else
           f"{sel['selected']} of the {sel['chosen']} poses chosen toured, ")
        + f"{sel['validation']} random validation poses added, "
        f"{sel['repeated_poses']} poses measured {sel['repeat_times']} times back to back (the noise floor)",
        f"predicted over {sample_text(p['sample']) if 'sample' in p else 'the suitable poses'}: "
        f"model vs truth {1e3 * p['model_position_mm']:.1f} µm mean position"
        + (f", {p['model_orientation_mrad']:.3f} mrad" if p.get("model_orientation_mrad") is not None
           else f" of the measured reflector{'s' if len(sel['measured']['reflectors']) > 1 else ''} (position only)")
        + f"; held-out {1e3 * p['heldout_position_mm']:.1f} µm "
          f"(tracker noise alone {1e3 * p['noise_position_mm']:.1f} µm)"])
