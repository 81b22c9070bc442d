"""Synthetic RGB-D scenes and an independent closure model, for tests, samples and benchmarks."""
