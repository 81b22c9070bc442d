"""Fitting the deformation model to observations, and calibration profiles on disk."""
