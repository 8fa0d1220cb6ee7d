"""The neural residual compensator (the paper's section 5)."""

from campaign.ann.network import ResidualNetwork, br_update, joint_mapping
from campaign.ann.selection import compensate_pose, cross_validate, fit_ann_stage

__all__ = ["ResidualNetwork", "br_update", "joint_mapping", "compensate_pose", "cross_validate", "fit_ann_stage"]
