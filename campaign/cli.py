"""The command line: a thin layer over the library (DESIGN.md, "The command line").

Each command module exposes ``register(subparsers)``, which adds its parser and sets
``func`` to a callable taking the parsed arguments. Every :class:`CampaignError` becomes
one line on stderr and exit code 1.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from campaign.errors import CampaignError

#: Modules that contribute sub-commands, in the order they appear in ``--help``.
COMMAND_MODULES = (
    "campaign.demo",
    "campaign.model.commands",
    "campaign.plan.commands",
    "campaign.measure.commands",
    "campaign.identify.commands",
    "campaign.sim.commands",
    "campaign.diagnose.commands",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="campaign",
        description="Plan, run and evaluate a laser-tracker calibration campaign of a 6-axis robot.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        rc = args.func(args)
    except CampaignError as exc:
        red, reset = ("\033[31m", "\033[0m") if sys.stderr.isatty() else ("", "")
        print(f"{red}campaign {args.command}: {exc}{reset}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"campaign {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
