"""Loaders that turn shipped real datasets into Contract 1 logs (``LogData``)."""
