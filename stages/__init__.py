"""Pipeline stages: each maps config parameters onto pipeline library calls."""
