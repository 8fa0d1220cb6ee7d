"""The neural residual compensator (the paper's section 5).

Modules: ``mlp`` (the network as flat weights, structured Jacobian products, mappings), ``lm``
(Bayesian-regularised Levenberg-Marquardt: the loop and its solver strategies), ``network``
(the estimator :class:`ResidualNetwork`, saving and loading), ``adam`` (many networks trained as
one batched computation), ``grid`` (the cross-validation grid over executors), ``selection``
(the sequential BR-LM cross-validation, pose compensation).
"""

from campaign.ann.lm import br_update
from campaign.ann.mlp import joint_mapping
from campaign.ann.network import ResidualNetwork
from campaign.ann.selection import compensate_pose, cross_validate, fit_ann_stage

__all__ = ["ResidualNetwork", "br_update", "joint_mapping", "compensate_pose", "cross_validate", "fit_ann_stage"]
