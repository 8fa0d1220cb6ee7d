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

from campaign.auto.decisions import decide, time_change_p, weak_structure_inputs
from campaign.auto.loop import auto
from campaign.auto.report import plot_rounds, verdict_text, write_auto_report
from campaign.auto.state import AutoOptions, AutoResult, CellSource, Decision, Limits, Round, state_path

__all__ = ["AutoOptions", "AutoResult", "CellSource", "Decision", "Limits", "Round", "auto", "decide", "plot_rounds",
           "state_path", "time_change_p", "verdict_text", "weak_structure_inputs", "write_auto_report"]
