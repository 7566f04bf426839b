"""Calibration: measured data, residual diagnostics, effect selection and reports."""
