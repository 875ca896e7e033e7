"""Calibration targets the twin can photograph instead of a sample (issue #16): printed boards at poses in the
rig's world frame, imaged through a rig camera's full model (intrinsics, distortion, pose)."""
