"""`campaign serve`: a cell's controller and tracker adapters on two TCP ports (docs/cell.md)."""

from __future__ import annotations


def register(sub):
    from campaign.cell.arguments import add_serve_arguments

    s = sub.add_parser(
        "serve", help="serve a cell's controller and tracker adapters (your robot, your tracker) over the protocol",
        description="Serve two adapter classes (docs/cell.md) as the robot controller and the laser tracker of "
                    "docs/protocol.md on two TCP ports, until Ctrl-C: framing, request ids, the reply cache, "
                    "heartbeats, error replies, joint limits and a move timeout are done here. Beyond loopback "
                    "every frame is authenticated with --token-file. Drive it with `campaign run RUN --controller "
                    "HOST:PORT --tracker HOST:PORT [--token-file FILE]`; `campaign run RUN --cell SPEC` starts "
                    "and stops it for you.")
    add_serve_arguments(s)
    s.set_defaults(func=_serve)


def _serve(args):
    import contextlib

    from campaign.cell.server import serve_until_interrupted, served_cell_from_args
    from campaign.run import RunFolder

    lock = RunFolder(args.run).sim_lock("serve") if args.run else contextlib.nullcontext()
    with lock:
        _, cell = served_cell_from_args(args)
        auth = "frames authenticated with the token" if cell.key is not None else "loopback, no token"
        print(f"cell: controller {args.controller} on {args.host}:{cell.controller_port}, tracker {args.tracker} on "
              f"{args.host}:{cell.tracker_port} ({auth}); Ctrl-C stops", flush=True)
        return serve_until_interrupted(cell)
