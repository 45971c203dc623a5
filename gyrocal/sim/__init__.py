"""gyrocal.sim."""
