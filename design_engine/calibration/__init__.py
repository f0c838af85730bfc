"""Material calibration through the engine: least squares with covariance; hinge,
oscillation and pulse models."""
