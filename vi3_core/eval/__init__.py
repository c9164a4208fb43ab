"""Evaluation: the paper's metrics, paper-like reports, plots, TUM export and the evaluation runner."""
