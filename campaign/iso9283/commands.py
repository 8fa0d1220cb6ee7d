"""`campaign iso9283 RUN [--calibrated RUN2] [--json]`: the ISO 9283 figures of a measured test run."""

from __future__ import annotations


def register(sub):
    p = sub.add_parser("iso9283", help="ISO 9283 pose accuracy (AP) and repeatability (RP) of a run planned with "
                                       "`campaign plan --iso9283`, nominal and calibrated")
    p.add_argument("run", metavar="RUN", help="the measured test run (plan --iso9283, then run)")
    p.add_argument("--calibrated", metavar="RUN2", default=None,
                   help="a second run of the same test planned with --compensate CALIBRATED_RUN and measured: "
                        "its figures are the calibrated ones")
    p.add_argument("--json", action="store_true", help="print RUN/iso9283/report.json instead of the table")
    p.set_defaults(func=_iso9283)


def _iso9283(args):
    from campaign.fileio import strict_json
    from campaign.iso9283.report import iso9283_report, table_text

    doc = iso9283_report(args.run, args.calibrated)
    if args.json:
        print(strict_json(doc))
    else:
        print(table_text(doc))
        print(f"written: {args.run}/iso9283/report.json, report.html")
    return 0
