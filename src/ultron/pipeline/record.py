"""``run.json``'s schema: :class:`RunRecord`, one typed record per run directory.

A run directory (``reconstruct``, ``finetune``) ends with ``run.json``, written last so that
its presence marks a finished run. Its first entry names the schema, ``"schema":
"ultron-run/1"``; then come the run's identity (``command``, ``method``, ``label_fraction``,
``seed``, ``dataset_dir`` — optional: it may be removed from a run directory that is shared;
``model_dir`` and ``model_method`` for a fine-tuning run), the mesh's size (``mesh``:
vertices, faces, area_mm2, coordinates), the acoustic field used (``field_dir``,
``field_cached``, ``field_dataset_match``; absent for methods without a field), the method's
own account (label selection, configurations, training logs, the grid, … — ``details``,
written at the top level of the file, one entry per key), where it computed (``device``),
``timings_s`` per stage with their ``total``, ``peak_rss_mb`` and the ``versions`` of the
libraries that shape the numbers.

Files written before the schema was recorded (no ``"schema"`` entry: schema version 0) are read
too: their ``command`` is inferred (:func:`run_kind`) and the entries they lack are None. A
schema this release does not know (a newer ultron's) is a one-line error naming the file.
"""

from __future__ import annotations

import json
import math
import platform
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from ultron import __version__, atomic
from ultron.errors import UltronInputError
from ultron.methods.catalog import FINETUNE_METHOD
from ultron.timing import StageTimer, peak_rss_mb

RUN_JSON = "run.json"
RUN_SCHEMA = "ultron-run/1"
RUN_KINDS = ("reconstruct", "finetune")

#: Entries of run.json that are fields of :class:`RunRecord` (everything else is ``details``).
_IDENTITY = ("command", "method", "label_fraction", "seed", "dataset_dir")
_FIELD = ("field_dir", "field_cached", "field_dataset_match")
_MODEL = ("model_dir", "model_method")
_TRAILER = ("device", "timings_s", "peak_rss_mb", "versions")


@dataclass(frozen=True)
class MeshSummary:
    """The written mesh's size and the coordinates of its files (``lps`` or ``ras``)."""

    vertices: int
    faces: int
    area_mm2: float
    coordinates: str = "lps"


@dataclass(frozen=True)
class RunRecord:
    """One run directory's ``run.json`` (module doc). ``details`` is the method's own account,
    written at the top level of the file; :meth:`to_dict` and :meth:`from_dict` round-trip."""

    command: str
    method: str
    label_fraction: float | None
    seed: int | None
    dataset_dir: str | None
    mesh: MeshSummary | None
    timings_s: dict[str, float]
    peak_rss_mb: float | None = None
    versions: dict[str, str] = field(default_factory=dict)
    device: dict[str, str] | None = None
    surface_evidence: dict[str, Any] | None = None
    field_dir: str | None = None
    field_cached: bool | None = None
    field_dataset_match: bool | None = None
    model_dir: str | None = None
    model_method: str | None = None
    details: dict[str, Any] = field(default_factory=dict)
    schema: str = RUN_SCHEMA

    @property
    def total_s(self) -> float:
        """The run's wall-clock seconds (``timings_s["total"]``, else the stages' sum)."""
        total = self.timings_s.get("total")
        return float(total) if total is not None else float(sum(self.timings_s.values()))

    def to_dict(self) -> dict[str, Any]:
        """run.json's content: schema, identity, mesh, evidence, details, field, trailer."""
        data: dict[str, Any] = {"schema": self.schema}
        data |= {name: getattr(self, name) for name in _IDENTITY}
        data |= {name: getattr(self, name) for name in _MODEL if getattr(self, name) is not None}
        if self.mesh is not None:
            data["mesh"] = {f.name: getattr(self.mesh, f.name) for f in fields(MeshSummary)}
        if self.surface_evidence is not None:
            data["surface_evidence"] = self.surface_evidence
        data |= {k: v for k, v in self.details.items() if k not in data}
        data |= {name: getattr(self, name) for name in _FIELD if getattr(self, name) is not None}
        data |= {name: getattr(self, name) for name in _TRAILER}
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str | Path = RUN_JSON) -> RunRecord:
        """The record of a run.json's content; an entry of the wrong type, a missing required
        one or an unknown schema is an :class:`UltronInputError` naming ``where``."""
        if not isinstance(data, Mapping):
            raise UltronInputError(where, RUN_JSON, "expected a JSON object")
        schema = data.get("schema")
        if schema is not None and schema != RUN_SCHEMA:
            raise UltronInputError(
                where, "schema", f"expected {RUN_SCHEMA!r} (or none: an older run), got"
                f" {schema!r}; was it written by a newer ultron?",
            )  # fmt: skip
        legacy = schema is None
        read = _Reader(data, where, required=not legacy)
        command = run_kind(data) if legacy else read.text("command")
        if command is None:
            raise UltronInputError(where, "command", f"expected one of {RUN_KINDS}, got none")
        mesh = read.mapping("mesh")
        known = {"schema", *_IDENTITY, *_FIELD, *_MODEL, *_TRAILER, "mesh", "surface_evidence"}
        return cls(
            command=command,
            method=read.text("method", required=True),
            label_fraction=read.number("label_fraction"),
            seed=read.integer("seed"),
            dataset_dir=read.text("dataset_dir", required=False),
            mesh=None if mesh is None else _mesh_summary(mesh, where),
            timings_s=read.numbers("timings_s"),
            peak_rss_mb=read.number("peak_rss_mb"),
            versions={str(k): str(v) for k, v in (read.mapping("versions") or {}).items()},
            device=read.mapping("device"),
            surface_evidence=read.mapping("surface_evidence", required=False),
            field_dir=read.text("field_dir", required=False),
            field_cached=read.flag("field_cached"),
            field_dataset_match=read.flag("field_dataset_match"),
            model_dir=read.text("model_dir", required=False),
            model_method=read.text("model_method", required=False),
            details={k: v for k, v in data.items() if k not in known},
            schema=RUN_SCHEMA if legacy else schema,
        )

    @classmethod
    def read(cls, run_dir: str | Path) -> RunRecord:
        """The record of ``run_dir/run.json``; a missing, unreadable or invalid file is an
        :class:`UltronInputError` naming it."""
        path = Path(run_dir) / RUN_JSON
        if not path.is_file():
            raise UltronInputError(path, RUN_JSON, "file is missing")
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise UltronInputError(path, RUN_JSON, f"not readable JSON ({exc})") from None
        return cls.from_dict(data, path)

    def write(self, run_dir: str | Path) -> Path:
        """Write ``run_dir/run.json`` atomically; returns its path."""
        path = Path(run_dir) / RUN_JSON
        atomic.write_json(path, self.to_dict())
        return path


def run_kind(run: Mapping[str, Any]) -> str | None:
    """The command that wrote a run.json's content, None if unknown. Files written before
    ``command`` was recorded are told apart by their method (``ultron-finetune``)."""
    command = run.get("command")
    if isinstance(command, str):
        return command
    method = run.get("method")
    if not isinstance(method, str):
        return None
    return "finetune" if method == FINETUNE_METHOD else "reconstruct"


def _mesh_summary(mesh: Mapping[str, Any], where: str | Path) -> MeshSummary:
    read = _Reader(mesh, where, required=True, prefix="mesh.")
    return MeshSummary(
        vertices=read.integer("vertices"),
        faces=read.integer("faces"),
        area_mm2=read.number("area_mm2"),
        coordinates=read.text("coordinates", required=False) or "lps",
    )


@dataclass(frozen=True)
class _Reader:
    """Typed reads of a JSON object's entries; ``required``: a missing entry is an error
    (schema 1), else None (an older file)."""

    data: Mapping[str, Any]
    where: str | Path
    required: bool
    prefix: str = ""

    def _get(self, name: str, required: bool | None) -> Any:
        value = self.data.get(name)
        if value is None and (self.required if required is None else required):
            raise UltronInputError(self.where, self.prefix + name, "is missing")
        return value

    def _wrong(self, name: str, expected: str, value: Any) -> UltronInputError:
        return UltronInputError(
            self.where, self.prefix + name, f"expected {expected}, got {value!r}"
        )

    def text(self, name: str, required: bool | None = None) -> str | None:
        value = self._get(name, required)
        if value is not None and not isinstance(value, str):
            raise self._wrong(name, "a string", value)
        return value

    def number(self, name: str, required: bool | None = None) -> float | None:
        value = self._get(name, required)
        if value is None:
            return None
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise self._wrong(name, "a finite number", value)
        return float(value)

    def integer(self, name: str, required: bool | None = None) -> int | None:
        value = self._get(name, required)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
            raise self._wrong(name, "an integer", value)
        return value

    def flag(self, name: str) -> bool | None:
        value = self.data.get(name)
        if value is not None and not isinstance(value, bool):
            raise self._wrong(name, "true or false", value)
        return value

    def mapping(self, name: str, required: bool | None = None) -> dict[str, Any] | None:
        value = self._get(name, required)
        if value is not None and not isinstance(value, Mapping):
            raise self._wrong(name, "an object", value)
        return None if value is None else dict(value)

    def numbers(self, name: str) -> dict[str, float]:
        """An object of finite numbers (``{}`` when absent from an older file)."""
        values = self.mapping(name) or {}
        inner = _Reader(values, self.where, required=True, prefix=f"{self.prefix}{name}.")
        return {str(key): inner.number(key) for key in values}


def versions() -> dict[str, str]:
    """Versions of ultron, Python and the libraries that shape the numbers."""
    import mcubes
    import numpy
    import scipy
    import torch
    import trimesh

    return {
        "ultron": __version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "torch": torch.__version__,
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "trimesh": trimesh.__version__,
        "pymcubes": getattr(mcubes, "__version__", "unknown"),
        "torch_threads": str(torch.get_num_threads()),
    }


def write_run_json(out_dir: Path, payload: dict[str, Any], timer: StageTimer) -> Path:
    """Write DIR/run.json (:class:`~ultron.pipeline.record.RunRecord`, checked against its
    schema before it is written) with the payload, timings, peak memory and versions."""
    data = {
        "schema": RUN_SCHEMA,
        **payload,
        "timings_s": {**timer.seconds, "total": timer.total},
        "peak_rss_mb": peak_rss_mb(),
        "versions": versions(),
    }
    return RunRecord.from_dict(data, Path(out_dir) / RUN_JSON).write(out_dir)
