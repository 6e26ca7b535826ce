"""Runs spread over Ray workers (``ray_runner``) and parameter searches (``tune``)."""
