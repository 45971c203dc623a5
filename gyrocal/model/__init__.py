"""gyrocal.model."""
