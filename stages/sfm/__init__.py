"""A small structure from motion shared by the calibrate stage (focal self-calibration) and
association (loop verification): features (SIFT with the user's masks, ratio-test matching),
tracks (RANSAC-verified matches chained over frames) and reconstruction (triangulation, PnP,
bundle adjustment with a shared focal length)."""
