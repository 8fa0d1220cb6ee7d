"""`campaign diagnose`: where the model fails and which physical effect is missing."""

from campaign.diagnose.engine import Diagnosis, diagnose

__all__ = ["Diagnosis", "diagnose"]
