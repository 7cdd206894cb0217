"""Tests of :mod:`torcsrl.policies`, one module per module of the package."""
