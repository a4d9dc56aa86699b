"""Accuracy report: plots (matplotlib, Agg) and a Markdown page."""
