"""Camera trackers: one estimator per module."""
