"""Demos and scenarios: the programs behind ``beehave demo`` and the README examples.

They use the ready-made library in :mod:`behaviours` but are not part of it.
"""
