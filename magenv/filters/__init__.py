"""Estimator kernels: pure step functions on plain arrays."""
