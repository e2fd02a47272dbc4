"""Writing meshes (PLY, STL, OBJ) and occupancy volumes (NIfTI), atomically.

Coordinates: ultron's world is read as LPS (3D Slicer's convention for model files since
4.11, and PLUS's). A mesh file is written in ``coordinates`` ``lps`` (world mm as is, the
default) or ``ras`` (x and y negated: a rotation by 180° about z, so face winding and outward
normals stay right), and says which in its header as 3D Slicer does — ``SPACE=LPS`` or
``SPACE=RAS`` in a PLY ``comment`` line, in the 80-byte header of a binary STL and in an OBJ's
first comment — so Slicer places either correctly; :func:`load_mesh` reads the tag back and
returns world (LPS) coordinates (an untagged file is LPS, as Slicer assumes). NIfTI is RAS by
definition: the NIfTI affine is the grid's world affine with x and y negated (LPS → RAS), so
mesh and volume open aligned in Slicer, and reading the volume with nibabel gives RAS
coordinates (−x, −y, z) of world points.

PLY files carry per-vertex properties when given (``vertex_attributes``, e.g. the evidence of
:mod:`ultron.mesh.evidence`); :func:`load_vertex_properties` reads them back.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ultron import atomic
from ultron.errors import UltronInputError, argument_error
from ultron.mesh.grid import GridSpec

MESH_FORMATS = (".ply", ".stl", ".obj")
MESH_COORDINATES = ("lps", "ras")
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
_FLIP_XY = np.array([-1.0, -1.0, 1.0])
_STL_HEADER_BYTES = 80


def check_mesh_coordinates(coordinates: str, name: str = "coordinates") -> str:
    """``coordinates`` if it is one of :data:`MESH_COORDINATES`, else an error naming
    ``name``."""
    if coordinates not in MESH_COORDINATES:
        raise argument_error(name, f"expected one of {MESH_COORDINATES}, got {coordinates!r}")
    return coordinates


def save_mesh(
    mesh,
    path: str | Path,
    coordinates: str = "lps",
    vertex_attributes: Mapping[str, np.ndarray] | None = None,
) -> Path:
    """Write ``mesh`` (world mm) to ``path`` in ``coordinates`` (``lps`` or ``ras``, tagged
    in the header); the format follows the suffix (.ply binary, .stl binary, .obj).
    ``vertex_attributes`` (name → (V,) array) become PLY vertex properties (other formats
    cannot hold them and ignore them). ``mesh`` itself is not modified."""
    import trimesh

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_FORMATS:
        raise argument_error("path", f"{path}: expected a suffix in {MESH_FORMATS}")
    space = check_mesh_coordinates(coordinates).upper()
    if len(mesh.faces) == 0:
        raise UltronInputError(path, "mesh", "refusing to write an empty mesh")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if space == "RAS":
        vertices = vertices * _FLIP_XY
    out = trimesh.Trimesh(vertices=vertices, faces=np.asarray(mesh.faces), process=False)
    for name, values in (vertex_attributes or {}).items():
        values = np.asarray(values)
        if values.shape != (len(vertices),):
            raise argument_error("vertex_attributes", f"{name!r}: expected ({len(vertices)},)")
        out.vertex_attributes[name] = values
    if suffix == ".obj":
        data = out.export(file_type="obj", header=f"ultron mesh, mm. SPACE={space}")
    else:
        data = out.export(file_type=suffix[1:])
    data = data if isinstance(data, bytes) else data.encode("utf-8")
    atomic.write_bytes(path, _tag_space(data, suffix, space))
    return path


def _tag_space(data: bytes, suffix: str, space: str) -> bytes:
    """Put ``SPACE=<space>`` where 3D Slicer looks for it (see the module docstring)."""
    tag = f"ultron mesh, mm. SPACE={space}".encode()
    if suffix == ".stl":  # the binary header: 80 free bytes
        return tag.ljust(_STL_HEADER_BYTES, b" ") + data[_STL_HEADER_BYTES:]
    if suffix == ".ply":  # a comment line after the format line, replacing trimesh's
        header, marker, body = data.partition(b"end_header\n")
        lines = [line for line in header.split(b"\n") if not line.startswith(b"comment")]
        lines.insert(2, b"comment " + tag)
        return b"\n".join(lines) + marker + body
    return data


def mesh_file_space(path: str | Path) -> str:
    """``lps`` or ``ras``: the ``SPACE=`` tag in the header of a mesh file (``lps`` when
    untagged, as 3D Slicer assumes)."""
    with open(path, "rb") as handle:
        head = handle.read(4096)
    if Path(path).suffix.lower() == ".ply":
        head = head.split(b"end_header", 1)[0]
    elif Path(path).suffix.lower() == ".obj":
        head = b"\n".join(line for line in head.split(b"\n") if line.startswith(b"#"))
    else:
        head = head[:_STL_HEADER_BYTES]
    return "ras" if b"SPACE=RAS" in head else "lps"


def load_mesh(path: str | Path, allow_empty: bool = False):
    """Read a mesh file as one ``trimesh.Trimesh`` in world (LPS) mm — a file tagged
    ``SPACE=RAS`` is converted (:func:`mesh_file_space`); a missing, unreadable or empty file
    is an error, and with ``allow_empty`` (an empty reconstruction, whose metrics are inf) still
    a file of vertices without triangles (a point cloud)."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise UltronInputError(path, "mesh", "file is missing")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise UltronInputError(path, "mesh", f"not a readable mesh ({exc})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise UltronInputError(path, "mesh", f"expected a triangle mesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0 and (not allow_empty or _holds_points(path)):
        raise UltronInputError(path, "mesh", "mesh is empty (no triangles)")
    if len(mesh.faces) == 0 and not _an_empty_mesh_file(path):
        raise UltronInputError(
            path, "mesh", f"not a readable mesh: no {path.suffix or 'mesh'} header or content"
        )
    if len(mesh.vertices) and not np.isfinite(mesh.vertices).all():
        raise UltronInputError(path, "mesh", "vertices contain NaN or inf")
    faces = np.asarray(mesh.faces)
    if faces.size and (faces.min() < 0 or faces.max() >= len(mesh.vertices)):
        raise UltronInputError(
            path, "mesh", f"a face names vertex {int(faces.max())} of {len(mesh.vertices)}"
            " (index out of range)",
        )  # fmt: skip
    if len(mesh.vertices) and mesh_file_space(path) == "ras":
        mesh.vertices = np.asarray(mesh.vertices, dtype=np.float64) * _FLIP_XY
    return mesh


#: The keywords of OBJ lines (and comments): an OBJ file with other lines is not one.
_OBJ_KEYWORDS = (b"#", b"v", b"vt", b"vn", b"vp", b"f", b"l", b"p", b"o", b"g", b"s", b"mtllib",
                 b"usemtl")  # fmt: skip


def _an_empty_mesh_file(path: Path) -> bool:
    """Whether ``path``, read as no triangles, is a mesh file of its format without any (what
    an empty reconstruction writes), not text or bytes of something else: a PLY or OFF header,
    an ASCII STL's ``solid`` or a binary STL of 0 triangles, an OBJ of OBJ lines alone."""
    data = path.read_bytes()
    suffix = path.suffix.lower()
    if suffix == ".stl":
        return data.lstrip().startswith(b"solid") or (
            len(data) == 84 and int.from_bytes(data[80:84], "little") == 0
        )
    if suffix == ".obj":
        words = (line.split(maxsplit=1) for line in data.splitlines())
        return all(not w or w[0] in _OBJ_KEYWORDS or w[0].startswith(b"#") for w in words)
    return data.lstrip().lower().startswith((b"ply", b"off"))


def _holds_points(path: Path) -> bool:
    """Whether a file that reads as a mesh without triangles holds vertices all the same (a
    point cloud: not a surface, never an empty reconstruction)."""
    import trimesh

    try:
        loaded = trimesh.load(path, process=False)
    except Exception:  # read once already; any doubt is settled by the caller's error
        return True
    return len(getattr(loaded, "vertices", ())) > 0


def load_vertex_properties(path: str | Path) -> dict[str, np.ndarray]:
    """The per-vertex properties of a PLY file other than x, y, z (name → (V,) array); empty
    for a file without any or another format."""
    mesh = load_mesh(path, allow_empty=True)
    raw = mesh.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    if raw is None or raw.dtype.names is None:
        return {}
    return {name: np.asarray(raw[name]) for name in raw.dtype.names if name not in "xyz"}


def nifti_affine(grid: GridSpec) -> np.ndarray:
    """The NIfTI (RAS) affine of ``grid``: LPS_TO_RAS @ grid.affine."""
    return LPS_TO_RAS @ grid.affine


def save_volume_nifti(volume: np.ndarray, grid: GridSpec, path: str | Path) -> Path:
    """Write a float32 volume on ``grid`` as NIfTI-1 (``.nii`` or ``.nii.gz``), aligned for Slicer."""
    import nibabel as nib

    path = Path(path)
    if not (path.name.endswith(".nii") or path.name.endswith(".nii.gz")):
        raise argument_error("path", f"{path}: expected a .nii or .nii.gz file name")
    if volume.shape != grid.shape:
        raise argument_error("volume", f"expected shape {grid.shape}, got {volume.shape}")
    image = nib.Nifti1Image(np.asarray(volume, dtype=np.float32), nifti_affine(grid))
    image.header.set_xyzt_units("mm")
    image.set_qform(nifti_affine(grid), code=1)
    image.set_sform(nifti_affine(grid), code=1)
    data = image.to_bytes() if path.name.endswith(".nii") else _gzip(image.to_bytes())
    atomic.write_bytes(path, data)
    return path


def _gzip(data: bytes) -> bytes:
    import gzip

    return gzip.compress(data, compresslevel=6, mtime=0)
