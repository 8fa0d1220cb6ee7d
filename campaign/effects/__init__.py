"""Physical effects that a user can add to the model (see campaign.effects.base)."""

from campaign.effects.base import Effect, EffectSet, available, make_effect, model_pose, register

__all__ = ["Effect", "EffectSet", "available", "make_effect", "model_pose", "register"]
