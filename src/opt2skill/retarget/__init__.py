"""Human motion to Digit references (`opt2skill retarget`): readers (BVH, AMASS-style SMPL(-H) .npz),
keypoints, calibration to Digit, QP IK, filtering, records. docs/baselines.md."""
