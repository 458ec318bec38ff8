"""Rendered synthetic scenes and correspondences with exact ground truth, and the demo dataset."""
