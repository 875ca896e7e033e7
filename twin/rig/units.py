"""Units and frames, stated once for the whole project.

Length
    **Millimetres** everywhere inside the twin (rig files, kernels, samples, captures). This is the unit
    of the released OpenSVBRDF configuration (`lights.bin`, `extrinsic.yml`; reference §1.6), so an
    imported rig needs no conversion. Conversion happens only at the edges: the physical radiometric
    convention of the forward model (`twin.optics.forward`) converts distances to metres, and user files may
    declare `length_unit = "m"`, which `twin.rig.format` converts on load.

World frame
    Right-handed, **+z out of the sample** (up), the frame of the released device files: the sample plane
    is z = -122 mm, the primary camera sits at about (3.7, 4.7, 289) mm looking down -z, the cube's walls
    are at x ~ -389 / +295 and y ~ +/-355 mm (reference §1.3-1.6).

Cameras
    OpenCV convention: X_cam = R @ X_world + t; camera +x right, +y down, +z forward along the optical
    axis; pixel (u, v) = (column, row) with the centre of the top-left pixel at (0, 0); the 5 distortion
    coefficients are (k1, k2, p1, p2, k3).

LED normals
    Unit emission normals pointing **into** the cube (towards the sample). The released files store them
    outward; the importer flips them (reference §1.2).
"""
from __future__ import annotations

LENGTH_UNIT = "mm"
MM_PER = {"mm": 1.0, "m": 1000.0}


def to_mm(value, unit: str):
    """Convert a length (scalar or array) given in `unit` to millimetres."""
    try:
        return value * MM_PER[unit]
    except KeyError:
        raise ValueError(f"unknown length unit {unit!r}; expected one of {sorted(MM_PER)}") from None


def mm_to_m(value):
    return value * 1e-3
