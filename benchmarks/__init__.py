"""Benchmark scripts run from a checkout (never as tests, never installed).

``cparticles bench`` itself lives in :mod:`cparticles.bench`, so it works from an
installed wheel.
"""
