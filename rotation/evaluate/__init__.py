"""Evaluation under perturbations: metrics, suites, reports, plots and videos."""
