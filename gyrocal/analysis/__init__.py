"""gyrocal.analysis."""
