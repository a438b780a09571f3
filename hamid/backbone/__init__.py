"""Backbone curves: the fitted model's frequency and damping ratio against amplitude."""
