"""Front ends: from an RGB-D frame to correspondences and pose hypotheses."""
