"""The rig: what the device is (LED positions, normals, profiles and intensities; boards; the cameras'
calibration; the sample plane; the holder frame with its markers), its folder format, the built-in rigs and
the importer of the released OpenSVBRDF configuration. Units and frames: twin.rig.units."""
from twin.rig.model import Rig, RigError

__all__ = ["Rig", "RigError"]
