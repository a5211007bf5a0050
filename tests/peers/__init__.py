"""Interoperability peers of the tests and the serial benchmark (see fixtures.py)."""
