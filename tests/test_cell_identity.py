"""Issue 31, part 5: a run is measured on one cell; resuming on another is refused in one line
unless the user says so, which the run records."""

import yaml

from campaign.cli import main
from campaign.measure.store import open_run


def _stored(runs, run):
    return len(runs.stored(run))


def test_a_run_resumed_on_another_cell_is_refused_unless_allowed_and_then_recorded(runs, capsys):
    run = runs.make(n=12)
    assert main(["run", str(run), "--sim", "--quiet", "--max-poses", "4"]) == 0
    with open_run(run) as store:
        first = store.get_meta("cell")
    assert first["kind"] == "sim" and first["spec"] == "--sim" and len(first["fingerprint"]) == 16
    capsys.readouterr()

    # the MuJoCo twin is another cell: refused before it is started, nothing stored
    assert main(["run", str(run), "--cell", "mujoco", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "measured so far on another cell (--sim" in err[0] and "--allow-other-cell" in err[0]
    assert _stored(runs, run) == 4 and not (run / "cell").exists()

    # the simulated cell with another world (its seed draws the hidden truth) is another cell too
    cfg = yaml.safe_load((run / "campaign.yaml").read_text())
    cfg["sim"]["seed"] = 7
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["run", str(run), "--sim", "--quiet", "--max-poses", "4"]) == 1
    err = capsys.readouterr().err
    # the same words (--sim) on both sides: the line says what differs, in campaign.yaml's words
    assert "measured so far on another cell" in err and "sim.seed 0 -> 7" in err and _stored(runs, run) == 4
    # ... but its faults are not: they leave the world as it was
    cfg["sim"]["seed"], cfg["sim"]["faults"] = 0, {"drop": 0.0}
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["run", str(run), "--sim", "--quiet", "--max-poses", "4"]) == 0 and _stored(runs, run) == 8

    # said explicitly: measured there, and the change is in the run's log
    cfg["sim"]["seed"] = 7
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["run", str(run), "--sim", "--quiet", "--allow-other-cell"]) == 0 and _stored(runs, run) == 12
    with open_run(run) as store:
        changed = store.events("cell_changed")
        cells = store.get_meta("cells")
        now = store.get_meta("cell")
    assert len(changed) == 1 and changed[0][3]["allowed_by"] == "--allow-other-cell"
    assert changed[0][3]["from"]["fingerprint"] == first["fingerprint"] == cells[0]["fingerprint"]
    assert now["fingerprint"] != first["fingerprint"] and cells[-1] == now and len(cells) == 2
