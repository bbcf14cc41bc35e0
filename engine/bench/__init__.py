"""The batch benchmark runner: matrices, measurement, results, reports and plots, the per-ray floor."""
