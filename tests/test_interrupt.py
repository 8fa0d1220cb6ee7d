"""A Ctrl-C that a library swallows (campaign.interrupt): raised again at the next stage boundary.

The library here is written in the test: a stage that catches BaseException around its work, as
trimesh's mesh code does, while a real SIGINT arrives (os.kill to this process)."""

import os
import signal

import pytest

from campaign import interrupt


@pytest.fixture(autouse=True)
def python_default_sigint():
    """Python's own SIGINT handler, whatever this process inherited (a job started in the background
    of a shell without job control ignores SIGINT, and Python then installs no handler)."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def swallowing_stage():
    try:
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(10_000):  # the handler runs between bytecodes of the main thread
            pass
    except BaseException:  # noqa: BLE001 - the library's habit under test
        return "swallowed"
    return "not interrupted"


def test_a_swallowed_ctrl_c_is_raised_at_the_next_check():
    interrupt.install()
    try:
        assert swallowing_stage() == "swallowed"
        with pytest.raises(KeyboardInterrupt):
            interrupt.check()
        interrupt.check()  # once: nothing pending any more
    finally:
        interrupt.uninstall()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_without_the_handler_the_interrupt_is_lost():
    """The reason for the module: Python's default handler leaves no trace once swallowed."""
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert swallowing_stage() == "swallowed"
    interrupt.check()  # nothing recorded: no exception


def test_plan_stops_at_the_stage_after_a_swallowed_interrupt(tmp_path, monkeypatch, capsys):
    """`campaign plan` with a filter stage that swallows a real SIGINT: the plan stops with one line
    and exit 130 instead of finishing (3 of 9 trials finished normally before)."""
    from campaign.cli import main
    from campaign.plan import checks

    calls = []
    wrapped = checks.range_ok  # the first filter of every chunk of the grid

    def swallowing(*a, **k):
        if not calls:
            calls.append(swallowing_stage())
        return wrapped(*a, **k)

    monkeypatch.setattr(checks, "range_ok", swallowing)
    rc = main(["plan", "--run", str(tmp_path / "r"), "--grid-scale", "0.4", "--select", "20", "--quiet"])
    err = capsys.readouterr().err
    assert calls == ["swallowed"], "the stage under test did not run"
    assert rc == 130 and err.strip().splitlines()[-1] == "campaign plan: interrupted", err
