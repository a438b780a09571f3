"""Backbone curves: the free periodic orbits of a fitted model, their frequency and equivalent
damping against amplitude, with bands."""
