"""A cell run by programs (docs/programs.md): the planned campaign as a robot program
(one module per controller language), the stops a tracker's log is matched to, and programs
filtered through a calibration.

``stops.py`` is the contract between them: ``RUN/program/stops.csv`` lists every stop of the
program in the order `campaign run` visits them.
"""
