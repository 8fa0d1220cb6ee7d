"""Thermal expansion of the arm with the cell temperature."""

from __future__ import annotations

import numpy as np

from campaign.effects.base import Effect, register

REFERENCE_TEMPERATURE_C = 20.0


@register
class Thermal(Effect):
    """All link lengths grow by α (T − 20 °C): the tool position scales about the base.

        t' = t + α (T − T_ref) · t     (T from the per-pose context ``temperature_c``)

    A constant temperature would be indistinguishable from a length error (the geometric
    parameters absorb it); the effect is identifiable from the temperature's variation.
    """

    name = "thermal"
    description = "thermal expansion: link lengths grow by α·(T − 20 °C)"
    context_keys = ("temperature_c",)
    param_names = ("alpha",)
    param_units = ("1/K",)

    def pose_map(self, params, T, q, context):
        dT = np.asarray(context["temperature_c"], dtype=float) - REFERENCE_TEMPERATURE_C
        out = np.array(T, dtype=float, copy=True)
        out[:, :3, 3] *= (1.0 + params[0] * dT)[:, None]
        return out

    def typical_params(self, seed=0):
        """Aluminium arm: 2.3e-5 1/K."""
        return np.array([2.3e-5])

    def synthetic_context(self, n, seed=0):
        """A day's temperature swing over the campaign: 20 ± 5 °C, slowly varying, with 0.1 K sensor noise."""
        rng = np.random.default_rng(seed + 23)
        phase = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return {"temperature_c": 20.0 + 5.0 * np.sin(phase + rng.uniform(0, 2 * np.pi)) + rng.normal(0, 0.1, n)}
