"""Synthetic point clouds with exact truth, for tests and benchmarks."""
