"""gyrocal.drivers."""
