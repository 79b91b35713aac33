"""Evaluation: the paper's methods and comparison, figures."""
