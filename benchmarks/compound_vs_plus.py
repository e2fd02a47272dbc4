"""Benchmark: ``ultron compound`` against the volume PLUS itself reconstructed from a recording.

On the PLUS spine phantom (``../shared/data/plus-spine-phantom``: 21 tracked frames of
820 × 616 and ``SpinePhantomFreehandReconstructed.mha``, 147 × 106 × 104 voxels of 0.5 mm):

1. ``ultron import-plus`` the sequence into a temporary dataset, in the frame PLUS reconstructed
   in (the ``VolumeReconstruction`` element's ``ReferenceCoordinateFrame``, PLUS's default
   ``Reference``; PLUS's volume origin is the lowest corner of the frames in that frame), with
   its blank columns kept (``--keep-blank-columns``) as PLUS's whole-frame clip rectangle
   keeps them;
2. ``ultron compound`` it with the settings of that element (``OutputSpacing``,
   ``Interpolation``, ``CompoundingMode``, ``FillHoles`` with a ``STICK`` element's
   ``StickLengthLimit``);
3. resample our NIfTI (RAS affine, world read as LPS) trilinearly onto PLUS's grid (MetaImage
   ``Offset``, ``ElementSpacing``, ``TransformMatrix``; world = PLUS's reference frame, also LPS)
   and compare the voxels both fill: a voxel of PLUS's volume is filled when its grey level is
   > 0 (PLUS writes 0 where nothing arrived, and the frames' black margins are 0 as well, so
   they drop out), one of ours when all 8 voxels the resampling reads are > 0;
4. print the normalised cross-correlation (target ≥ 0.9) and the mean absolute grey-level
   difference, then the same figures for volumes compounded directly on PLUS's grid (no
   resampling): with the dataset's rigid pixel → world map, with PLUS's own sheared
   ``Image → Probe`` map (what the importer's rigid factorisation, residual ≤ 0.96 mm at the
   corners, costs), and with PLUS's stick weighting as well.

Usage::

    python benchmarks/compound_vs_plus.py [--data ../shared/data/plus-spine-phantom]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "plus-spine-phantom"
SEQUENCE = "SpinePhantomFreehand.igs.mha"
CONFIG = "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"
RECONSTRUCTED = "SpinePhantomFreehandReconstructed.mha"
INTERPOLATION = {"LINEAR": "linear", "NEAREST_NEIGHBOR": "nearest"}
COMPOUNDING = {"MEAN": "mean", "MAXIMUM": "max"}


@dataclass(frozen=True)
class PlusSettings:
    """PLUS's volume-reconstruction settings, in ``ultron compound``'s terms."""

    frame: str
    spacing_mm: float
    interpolation: str
    reduce: str
    fill_holes: int

    def options(self) -> list[str]:
        return [
            "--spacing", f"{self.spacing_mm:g}", "--interpolation", self.interpolation,
            "--reduce", self.reduce, "--fill-holes", str(self.fill_holes),
        ]  # fmt: skip


def read_settings(config: Path) -> PlusSettings:
    """The ``VolumeReconstruction`` element of a PLUS configuration."""
    element = ET.parse(config).getroot().find(".//VolumeReconstruction")
    if element is None:
        raise SystemExit(f"{config}: no VolumeReconstruction element")
    spacing = {float(s) for s in element.get("OutputSpacing", "1 1 1").split()}
    if len(spacing) != 1:
        raise SystemExit(f"{config}: OutputSpacing {spacing} is not isotropic")
    fill = 0
    if element.get("FillHoles", "OFF").upper() == "ON":
        sticks = [e for e in element.iter("HoleFillingElement") if e.get("Type") == "STICK"]
        if not sticks or sticks[0].get("NumberOfSticksToUse", "1") != "1":
            raise SystemExit(f"{config}: only one STICK hole-filling element is supported")
        fill = int(sticks[0].get("StickLengthLimit", "9"))
    return PlusSettings(
        frame=element.get("ReferenceCoordinateFrame", "Reference"),
        spacing_mm=spacing.pop(),
        interpolation=INTERPOLATION[element.get("Interpolation", "NEAREST_NEIGHBOR").upper()],
        reduce=COMPOUNDING[element.get("CompoundingMode", "MEAN").upper()],
        fill_holes=fill,
    )


@dataclass(frozen=True)
class PlusVolume:
    """A PLUS MetaImage volume as (x, y, z) grey levels and its voxel → world (LPS) map."""

    values: np.ndarray
    index_to_world: np.ndarray


def read_plus_volume(path: Path) -> PlusVolume:
    """A 3D uint8 MetaImage (raw or zlib) with its Offset, ElementSpacing, TransformMatrix."""
    from ultron.data.plus import read_metaimage_header

    fields, offset = read_metaimage_header(path)
    sizes = [int(s) for s in fields["DimSize"].split()]
    if fields.get("ElementType") != "MET_UCHAR" or len(sizes) != 3:
        raise SystemExit(f"{path}: expected a 3D MET_UCHAR volume")
    payload = path.read_bytes()[offset:]
    if fields.get("CompressedData", "False").lower() == "true":
        payload = zlib.decompress(payload)
    values = np.frombuffer(payload, np.uint8, count=int(np.prod(sizes)))
    values = values.reshape(sizes[::-1]).transpose(2, 1, 0)
    direction = np.array(
        [float(v) for v in fields.get("TransformMatrix", "1 0 0 0 1 0 0 0 1").split()]
    )
    spacing = np.array([float(v) for v in fields["ElementSpacing"].split()])
    affine = np.eye(4)
    affine[:3, :3] = direction.reshape(3, 3).T * spacing  # MetaImage: column-major direction
    affine[:3, 3] = [float(v) for v in fields["Offset"].split()]
    return PlusVolume(values.astype(np.float32), affine)


def plus_grid(plus: PlusVolume):
    """PLUS's grid as a GridSpec (axis-aligned volumes only)."""
    from ultron.mesh.grid import GridSpec

    linear = plus.index_to_world[:3, :3]
    voxel = float(linear[0, 0])
    if not np.allclose(linear, np.eye(3) * voxel):
        raise SystemExit("PLUS's volume is not axis-aligned and isotropic")
    origin = tuple(float(o) for o in plus.index_to_world[:3, 3])
    return GridSpec(origin, voxel, tuple(int(n) for n in plus.values.shape))


def resample_nifti(path: Path, plus: PlusVolume) -> tuple[np.ndarray, np.ndarray]:
    """Our NIfTI's grey levels at PLUS's voxel centres (trilinear) and where all 8 voxels read
    are filled (> 0)."""
    import nibabel as nib
    from scipy import ndimage

    image = nib.load(path)
    data = np.asarray(image.dataobj, dtype=np.float32)
    lps_to_ras = np.diag([-1.0, -1.0, 1.0, 1.0])
    to_ours = np.linalg.inv(image.affine) @ lps_to_ras @ plus.index_to_world
    ijk = np.indices(plus.values.shape).reshape(3, -1).astype(np.float64)
    coords = to_ours[:3, :3] @ ijk + to_ours[:3, 3:4]
    values = ndimage.map_coordinates(data, coords, order=1, cval=0.0)
    filled = ndimage.map_coordinates((data > 0).astype(np.float32), coords, order=1, cval=0.0)
    shape = plus.values.shape
    return values.reshape(shape), (filled > 1 - 1e-6).reshape(shape)


def compare(ours: np.ndarray, ours_filled: np.ndarray, plus: np.ndarray) -> dict[str, float]:
    """NCC and mean absolute difference on the voxels both fill."""
    both = ours_filled & (plus > 0)
    a, b = ours[both].astype(np.float64), plus[both].astype(np.float64)
    a0, b0 = a - a.mean(), b - b.mean()
    ncc = float((a0 * b0).sum() / np.sqrt((a0 * a0).sum() * (b0 * b0).sum()))
    return {"ncc": ncc, "mad": float(np.abs(a - b).mean()), "voxels": int(both.sum()),
            "plus_filled": int((plus > 0).sum())}  # fmt: skip


def exact_plus_samples(dataset_dir: Path, chunk_frames: int = 4):
    """Samples of every pixel mapped by PLUS's own (sheared) Image → Probe matrix:
    pose_k · D⁻¹ · ImageToProbe · [c, r, 0, 1], D the importer's rigid dataset-probe → probe
    map (rebuilt from the fitted matrix in dataset.json)."""
    import torch

    from ultron.data.dataset import SweepDataset

    dataset = SweepDataset.load(dataset_dir)
    (sweep,) = dataset.sweeps
    meta = json.loads((dataset_dir / "dataset.json").read_text())["metadata"]["imports"][sweep.name]
    if meta["orientation"][:2] != "MF" or meta["downsample"] != 1:
        raise SystemExit("the exact map here handles MF frames at full size only")
    calibration = np.asarray(meta["image_to_probe"])
    clip = (meta.get("clip") or {}).get("origin", [0, 0])
    calibration[:3, 3] += clip[0] * calibration[:3, 0] + clip[1] * calibration[:3, 1]
    fitted = np.asarray(meta["fitted_image_to_probe"])
    rigid = np.eye(4)
    rigid[:3, :3] = fitted[:3, :3] / np.linalg.norm(fitted[:3, :3], axis=0)
    rigid[:3, 3] = fitted[:3, 3] + dataset.probe.width_px / 2 * fitted[:3, 0]
    h, w = dataset.probe.image_shape
    r, c = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    pixels = np.stack([c.ravel(), r.ravel(), np.zeros(r.size), np.ones(r.size)]).astype(np.float64)
    for start in range(0, sweep.n_frames, chunk_frames):
        poses = sweep.probe_to_world[start : start + chunk_frames] @ np.linalg.inv(rigid)
        points = np.einsum("nij,jp->npi", (poses @ calibration)[:, :3], pixels)
        values = sweep.images[start : start + chunk_frames].reshape(len(poses), -1)
        yield torch.from_numpy(points.reshape(-1, 3)), torch.from_numpy(values.ravel())


def ultron(*args: str) -> str:
    """Run the ultron CLI, fail loudly, return its output."""
    cmd = [sys.executable, "-m", "ultron.cli.main", *args]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stdout}{done.stderr}")
    return done.stdout


def direct_comparisons(dataset_dir: Path, settings: PlusSettings, plus: PlusVolume) -> None:
    """Compound directly on PLUS's grid (no resampling) with both pixel → world maps."""
    from ultron.data.dataset import SweepDataset
    from ultron.mesh.image_compounding import (
        ImageCompoundingConfig,
        compound_images,
        compound_samples,
    )
    from ultron.mesh.splat import SplatConfig

    grid = plus_grid(plus)
    config = ImageCompoundingConfig(
        settings.spacing_mm, SplatConfig(settings.interpolation, settings.reduce),
        settings.fill_holes,
    )  # fmt: skip
    runs = {
        "ultron's rigid map, on PLUS's grid": lambda: compound_images(
            SweepDataset.load(dataset_dir), config, grid=grid
        ),
        "PLUS's sheared map, on PLUS's grid": lambda: compound_samples(
            exact_plus_samples(dataset_dir), grid, config
        ),
        "PLUS's map and stick weights": lambda: compound_samples(
            exact_plus_samples(dataset_dir), grid, replace(config, plus_weights=True)
        ),
    }
    for name, run in runs.items():
        result = run()
        figures = compare(result.volume, result.filled | result.hole_filled, plus.values)
        print(f"  {name:38s} NCC {figures['ncc']:.4f}  mean |Δ| {figures['mad']:.2f} grey levels"
              f"  ({figures['voxels']} voxels)")  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA, help="the PLUS spine-phantom folder")
    args = parser.parse_args()
    settings = read_settings(args.data / CONFIG)
    plus = read_plus_volume(args.data / RECONSTRUCTED)
    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        ultron("import-plus", str(args.data / SEQUENCE), "--config", str(args.data / CONFIG),
               "--to", settings.frame, "--keep-blank-columns", "--out", str(tmp / "dataset"))  # fmt: skip
        options = [str(tmp / "dataset"), *settings.options(), "--out", str(tmp / "volume.nii.gz")]
        start = time.perf_counter()
        ultron("compound", *options)
        seconds = time.perf_counter() - start
        values, filled = resample_nifti(tmp / "volume.nii.gz", plus)
        figures = compare(values, filled, plus.values)
        print(f"PLUS settings: {settings}")
        print(
            f"ultron compound DATASET {' '.join(options[1:-2])} --out VOLUME.nii.gz: {seconds:.1f} s"
        )
        print(
            f"vs {RECONSTRUCTED}, resampled onto its grid: NCC {figures['ncc']:.4f} (target ≥ 0.9),"
            f" mean |Δ| {figures['mad']:.2f} grey levels over {figures['voxels']} voxels both fill"
            f" (PLUS fills {figures['plus_filled']})"
        )
        print("the same settings compounded directly on PLUS's grid:")
        direct_comparisons(tmp / "dataset", settings, plus)
    return 0 if figures["ncc"] >= 0.9 else 1


if __name__ == "__main__":
    sys.exit(main())
