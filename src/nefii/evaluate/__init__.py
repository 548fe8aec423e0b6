"""Evaluation as in the paper's Table 1: render test views, align albedo, compute metrics, report."""
