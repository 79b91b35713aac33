"""Estimating contact forces from readings: starts, the fit, count selection, the verdict, uncertainty, calibration."""
