"""Performance benchmarks (run as `cparticles bench`, never as tests)."""
