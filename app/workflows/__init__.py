"""Workflows the console and the CLI share: a calibration session, a calibration run, the TOF range
and thermal balance runs, and the report they print.
"""
