"""Evaluation of estimates against ground truth: metrics (numpy only) and plots (matplotlib)."""
