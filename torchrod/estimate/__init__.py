"""Estimating contact forces from readings: the options, the estimator and its verdicts, the noise learned from a
stream, calibration. The numerical work is the kernels' (:mod:`torchrod.kernels`)."""
