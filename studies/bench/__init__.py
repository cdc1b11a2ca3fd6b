"""Benchmarks run by ``rollingstar bench ...`` that score an analysis against known truth."""
