"""Placeholder replaced in the next commit by the ECC implementation."""
