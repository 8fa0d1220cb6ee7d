"""The model-free test looks at the residual in the frame after joint 1 and in the tool frame: an
effect in the wrist moves the tool point along a direction fixed in the tool frame, scaled by a
function of the wrist joints, which the flexible regressor finds there from one input (issue 31:
the open-world verdict names the right input first). The truth is read only after diagnose answered."""

import numpy as np

from campaign.diagnose import diagnose
from campaign.effects import Effect
from test_diagnose_open_world import make_open_run


class FlangeRunout(Effect):
    """The flange's bearing: joint 6's axis tilts about x of its frame by a sin(q6) + b cos(q6)."""

    name = "flange_runout"
    description = "bearing run-out of joint 6"
    param_names = ("a", "b")
    param_units = ("rad", "rad")

    def joint_twist(self, params, q, context):
        xi = np.zeros((len(q), q.shape[1], 6))
        xi[:, 5, 3] = params[0] * np.sin(q[:, 5]) + params[1] * np.cos(q[:, 5])
        return xi


def test_a_flange_run_out_is_unexplained_and_depends_on_q6_first(tmp_path, robot):
    run, truth, _ = make_open_run(tmp_path, robot, [FlangeRunout(robot)], [3e-3, -2e-3], n=240)
    d = diagnose(run, folds=4, candidates="cyclic,joint_compliance,backlash")
    assert d.structure_significant and d.structure.heldout_gain > 0.5, d.text()
    assert d.verdict == "unexplained" and d.depends_on[:1] == ["q6"], d.text()
    # only now the truth: joint 6's axis tilts with q6, no catalogued effect
    assert [type(e).__name__ for e in truth.effects.effects] == ["FlangeRunout"]
