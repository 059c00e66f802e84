"""Scheduling of simulation: trajectory assembly, group stepping."""
