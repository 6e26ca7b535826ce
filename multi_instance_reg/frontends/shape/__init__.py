"""The shape front end: pose hypotheses from depth alone (point-pair votes, ECC, ICP) and one verification that chooses the instances (explain.py)."""
