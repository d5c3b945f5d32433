"""Evaluation reports: Allan deviation, drift before and after, positioning accuracy, plots."""
