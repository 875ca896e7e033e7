"""Calibration targets the twin can photograph instead of a sample (docs/calibration.md): a ChArUco board at poses
in the rig's world frame, a flat-field source, a diffuse plate (lifted on spacers, or the empty holder's acrylic lit
from below) and a ColorChecker, each imaged through a rig camera's full model (intrinsics, distortion, pose)."""
