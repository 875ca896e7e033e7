"""The reconstruction folder (`hemicube reconstruct -o OUT`), and its one owner: the pipeline writes it
through `ReconstructionFolder`, and whoever reads a finished one (validation, a batch over many captures)
reads it here; no other module knows its file names.

    reconstruction.json      format, version, config, network, timings (s) per stage, counts, and the sha256 of
                             every other file ("files"): written last, so a folder is finished when it verifies
    alignment.npz            the alignment map (primary pixel -> secondary pixel) and homography
    measurements.npz         the extracted measurements (reconstruction.extraction.Measurements)
    latent.exr               72 float32 channels L_0 ... L_71 (reference §4: [a_R, a_G, a_B, s])
    latent_passes.npz        the latents after each fine-tuning pass (pass0 ... pass3)
    maps/                    the fitted OpenSVBRDF maps (twin.materials.samples format: pd/ps/ax_ay/normal/
                             tangent/transparency textures, αx ≥ αy)
The pipeline assembles it in a temporary folder that replaces OUT only when complete
(twin.atomic.atomic_folder): a failed or killed run leaves the previous folder, or none.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from twin.atomic import atomic_path, file_sha256, write_bytes_atomic

FORMAT_NAME = "hemicube-reconstruction"
FORMAT_VERSION = 1
SUMMARY = "reconstruction.json"
ALIGNMENT = "alignment.npz"
MEASUREMENTS = "measurements.npz"
LATENT = "latent.exr"
LATENT_PASSES = "latent_passes.npz"
MAPS = "maps"


class ReconstructionFolder:
    def __init__(self, directory):
        self.dir = Path(directory)

    def _npz(self, name: str, **arrays) -> None:
        with atomic_path(self.dir / name, suffix=".npz") as tmp:
            np.savez(tmp, **arrays)

    def write_alignment(self, alignment) -> None:
        self._npz(ALIGNMENT, map=alignment.map, homography=alignment.homography)

    def write_measurements(self, meas) -> None:
        g = meas.grid
        self._npz(MEASUREMENTS, learned=meas.learned, lines=meas.lines, line_weights=meas.line_weights,
                  learned_photos=meas.learned_photos, learned_weights=meas.learned_weights,
                  transparency=meas.transparency, valid=meas.valid, pixel_primary=meas.pixel_primary,
                  pixel_secondary=meas.pixel_secondary, grid=np.array([g.resolution, g.size_mm], np.float64))

    def write_latent(self, latent: np.ndarray, grid_shape, passes: dict) -> None:
        from .latents import write_latent_exr

        write_latent_exr(self.dir / LATENT, latent, grid_shape)
        self._npz(LATENT_PASSES, **passes)

    def write_maps(self, maps) -> None:
        from twin.materials.samples import write_maps

        write_maps(maps, self.dir / MAPS)

    def _files(self) -> list[str]:
        return sorted(p.relative_to(self.dir).as_posix() for p in self.dir.rglob("*")
                      if p.is_file() and p.name != SUMMARY)

    def write_summary(self, summary: dict) -> None:
        """The summary, with the checksums of every file written before it (so: last)."""
        files = {rel: file_sha256(self.dir / rel) for rel in self._files()}
        doc = {"format": FORMAT_NAME, "version": FORMAT_VERSION, **summary, "files": files}
        write_bytes_atomic(self.dir / SUMMARY, json.dumps(doc, indent=1).encode())

    def verify(self) -> list[str]:
        """Files that are missing, changed or not listed (empty: a finished, intact reconstruction). A folder
        without a readable summary raises ValueError."""
        listed = self.summary().get("files", {})
        bad = [rel for rel, h in listed.items() if not (self.dir / rel).is_file() or file_sha256(self.dir / rel) != h]
        return sorted(bad + [rel for rel in self._files() if rel not in listed])

    def summary(self) -> dict:
        path = self.dir / SUMMARY
        try:
            doc = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"{self.dir}: not a finished reconstruction ({path.name}: {e})") from None
        if doc.get("format") != FORMAT_NAME or doc.get("version") != FORMAT_VERSION:
            raise ValueError(f"{path}: not a {FORMAT_NAME} v{FORMAT_VERSION} summary")
        return doc

    def maps(self):
        from twin.materials.samples import read_maps

        return read_maps(self.dir / MAPS)

    def latent(self) -> np.ndarray:
        """(R, C, 72) float32 final latents."""
        from .latents import read_latent_exr

        return read_latent_exr(self.dir / LATENT)
