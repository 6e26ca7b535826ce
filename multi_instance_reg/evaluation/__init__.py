"""Scoring 6D pose results as the BOP challenge does (VSD, MSSD, MSPD, AR) and with the
project's MHR / MHP / MHF1: ``bop_scoring.score_results``; the pose-error functions in
``pose_errors``; a depth-only triangle rasteriser in ``render``. No ROS."""
