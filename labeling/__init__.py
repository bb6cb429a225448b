"""Manual keypoint labeling in a local web page."""
