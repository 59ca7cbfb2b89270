"""Bridges to other libraries (GTSAM, evo); each import is optional."""
