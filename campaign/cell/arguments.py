"""The arguments of `campaign serve`, apart from the server so that `campaign --help` builds the
parser without importing numpy (campaign.cli: a command's register() stays cheap)."""

from __future__ import annotations


def add_serve_arguments(p, *, run_default=None) -> None:
    """The arguments of `campaign serve` (also `python -m campaign.cell.server`)."""
    p.add_argument("--controller", metavar="SPEC", required=True,
                   help="the controller adapter: sim, mujoco, FILE.py[:Class] (default class Controller), "
                        "package.module:Class, or an entry point of group campaign.cell")
    p.add_argument("--tracker", metavar="SPEC", required=True,
                   help="the tracker adapter (as --controller; default class Tracker)")
    p.add_argument("--options", metavar="FILE", default=None,
                   help="YAML with 'controller:' and 'tracker:' sections, given to the adapters")
    p.add_argument("--run", metavar="DIR", default=run_default,
                   help="the run served: its robot, configuration and campaign clock; the cell's own files go "
                        "there (RUN/sim/ for the simulator); one cell per run")
    p.add_argument("--config", metavar="FILE", default=None,
                   help="configuration (default: RUN/campaign.yaml, else the embedded one)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default: %(default)s; any other needs --token-file)")
    p.add_argument("--controller-port", type=int, default=0, help="controller port (default: any free port)")
    p.add_argument("--tracker-port", type=int, default=0, help="tracker port (default: any free port)")
    p.add_argument("--token-file", metavar="FILE", default=None,
                   help="shared secret: every frame is authenticated with it (HMAC-SHA256); required beyond "
                        "loopback; give the same file to `campaign run --token-file`")
    p.add_argument("--move-timeout-s", type=float, default=None,
                   help="longest move or measurement an adapter may take (default: the run's run.move_timeout_s)")
