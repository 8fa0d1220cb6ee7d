"""A slow drift of the measurement set-up over the campaign's time."""

from __future__ import annotations

import numpy as np

from campaign.effects.base import Effect, register


@register
class Drift(Effect):
    """The tool position drifts linearly with time (tracker or base creeping): t' = t + v · (time_s / 3600).

    Context: ``time_s`` (the campaign clock, always present in measured poses).
    """

    name = "drift"
    description = "drift over time: positions move by v·t (mm per hour scale)"
    context_keys = ("time_s",)
    param_names = ("v_x", "v_y", "v_z")
    param_units = ("m/h", "m/h", "m/h")

    def pose_map(self, params, T, q, context):
        hours = np.asarray(context["time_s"], dtype=float) / 3600.0
        out = np.array(T, dtype=float, copy=True)
        out[:, :3, 3] += hours[:, None] * np.asarray(params, dtype=float)[None, :]
        return out

    def typical_params(self, seed=0):
        """A tracker stand creeping ~5 µm per hour."""
        rng = np.random.default_rng(seed + 31)
        v = rng.normal(size=3)
        return 5e-6 * v / np.linalg.norm(v)
