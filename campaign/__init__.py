"""campaign: take a serial robot arm (any number of joints) and a laser tracker from an empty cell to a calibrated robot."""

__version__ = "0.1.0"
