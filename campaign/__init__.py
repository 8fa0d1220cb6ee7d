"""campaign: take a 6-axis robot and a laser tracker from an empty cell to a calibrated robot."""

__version__ = "0.1.0"
