"""gyrocal.daemon."""
