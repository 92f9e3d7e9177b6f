"""Placeholder package: see the issue tracker; empty until its issue lands."""
