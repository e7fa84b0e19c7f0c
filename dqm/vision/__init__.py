"""The image side of dqm: SIFT features, generated scenes, datasets with ground truth,
the OpenCV BF / FLANN baselines, and COLMAP import / export."""
