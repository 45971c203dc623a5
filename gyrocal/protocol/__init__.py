"""gyrocal.protocol."""
