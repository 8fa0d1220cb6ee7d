"""`campaign auto`: a campaign that measures until it understands the robot.

The loop (DESIGN.md: plan → measure → calibrate → diagnose → decide → measure more):

1. plan the short campaign when the run has none (:func:`campaign.plan.pipeline.plan_campaign`),
   measure it, calibrate the current model, diagnose it;
2. decide from the diagnosis (:func:`decide`, a pure function of the diagnosis, the calibration
   and the rounds before) and do it:

   * a candidate effect is significant (the verdict, or the part of an "unexplained" it
     explains) → add it to RUN/campaign.yaml, calibrate again;
   * at the noise floor, but the model's parameters poorly determined (the predicted mean
     position error of the model against the truth above the target) → the next poses by the
     plan's optimal design for the current model (:func:`campaign.plan.extend.design_poses`);
   * "unexplained" → poses that reveal its structure: spread over the inputs it depends on
     (:func:`campaign.plan.extend.spread_poses`), or measured poses measured again later when
     it depends on time (:func:`campaign.plan.extend.remeasure_poses`);
   * nothing more to learn → stop, saying which and why: at the floor; unexplained and the new
     poses no longer change the verdict; the budget or the pose limit reached.

New poses are appended to RUN/plan/poses.csv and measured by the same driver (every pose
without a stored outcome); every calibration appends to RUN/calibration/history.json. The
loop's state lives in RUN/auto/state.json, written atomically after every step, and each step
is idempotent: a decision is written before it is carried out and carried out again on resume
(an effect added twice is added once, a pose the plan holds is not appended again, the driver
measures only poses without a stored outcome), so a killed `auto` resumes where it stopped,
losing nothing and measuring nothing twice; every decision follows deterministically from the
stored data.
"""

# Lazy: `campaign --help` imports campaign.auto.commands, hence this package, and must not pull
# numpy in with the loop (tests/test_urdf_chain.py).
_WHERE = {"decide": "decisions", "weak_structure_inputs": "decisions",
          "auto": "loop", "plot_rounds": "report", "verdict_text": "report", "write_auto_report": "report",
          "AutoOptions": "state", "AutoResult": "state", "CellSource": "state", "Decision": "state",
          "Limits": "state", "Round": "state", "state_path": "state"}

__all__ = sorted(_WHERE)


def __getattr__(name):
    if name not in _WHERE:
        raise AttributeError(f"module 'campaign.auto' has no attribute {name!r}")
    import importlib
    return getattr(importlib.import_module(f"campaign.auto.{_WHERE[name]}"), name)
