"""Calibration: the staged start, the joint Schur LM, the covariance, the bound and the implicit derivative."""
