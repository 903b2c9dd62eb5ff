"""Simulated devices for tests and demos (never imported by production code)."""
