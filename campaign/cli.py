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
    "campaign.cell.commands",
    "campaign.diagnose.commands",
    "campaign.iso9283.commands",
    "campaign.auto.commands",
    "campaign.program.commands",
    "campaign.watch.commands",
)


class _Parser(argparse.ArgumentParser):
    """argparse with the package's error convention: a bad argument is one line on stderr and
    exit status 1 (``--help`` still shows the usage)."""

    def error(self, message):
        _one_line(self.prog.removeprefix("campaign").strip(), f"{message} (see {self.prog} --help)")
        sys.exit(1)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="campaign",
        description="Plan, run and evaluate a laser-tracker calibration campaign of any serial robot arm "
                    "(N joints, revolute or prismatic: a URDF, and a robot.yaml for what a URDF cannot say).",
    )
    parser.add_argument("--version", action="version", version=f"campaign {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def _version() -> str:
    """The installed distribution's version (the package's own when run from a source tree)."""
    from importlib import metadata

    try:
        return metadata.version("campaign")
    except metadata.PackageNotFoundError:
        from campaign import __version__

        return __version__


def _one_line(command, message) -> int:
    red, reset = ("\033[31m", "\033[0m") if sys.stderr.isatty() else ("", "")
    prefix = f"campaign {command}" if command else "campaign"
    print(f"{red}{prefix}: {' '.join(message.split())}{reset}", file=sys.stderr)
    return 1


def main(argv=None) -> int:
    from campaign import interrupt

    interrupt.install()  # a Ctrl-C that a library swallows is raised again at the next stage boundary
    try:
        return _main(argv)
    finally:
        interrupt.uninstall()


def _main(argv) -> int:
    try:  # the command modules' imports take seconds on a loaded machine: Ctrl-C there is one line too
        parser = build_parser()
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a bad argument (1, one line already printed)
        return int(exc.code or 0)
    except KeyboardInterrupt:
        print("campaign: interrupted", file=sys.stderr)
        return 130
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        rc = args.func(args)
    except CampaignError as exc:
        return _one_line(args.command, str(exc))
    except OSError as exc:  # the system refused (full disk, permissions, ...): where and why, in one line
        where = f"{exc.filename}: " if exc.filename else ""
        return _one_line(args.command, f"{where}{exc.strerror or exc}")
    except KeyboardInterrupt:
        print(f"campaign {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
