"""run.json's schema (:class:`ultron.pipeline.record.RunRecord`): round trip, older files,
and every kind of bad entry named in a one-line error."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ultron.errors import UltronInputError
from ultron.pipeline.record import RUN_SCHEMA, MeshSummary, RunRecord


def _schema_one() -> dict:
    return {
        "schema": RUN_SCHEMA,
        "command": "reconstruct",
        "method": "ultron",
        "label_fraction": 0.1,
        "seed": 3,
        "dataset_dir": "/data/L3",
        "mesh": {"vertices": 10, "faces": 16, "area_mm2": 12.5, "coordinates": "ras"},
        "surface_evidence": {"mesh": {"observed_share": 1.0}},
        "selection": {"fraction": 0.1, "frames": {"row": [1, 2]}},
        "occupancy_log": [{"step": 0, "loss": 0.7}],
        "field_dir": "/fields/L3",
        "field_cached": True,
        "field_dataset_match": None,
        "device": {"device": "cpu", "torch": "2.13.0+cpu"},
        "timings_s": {"occupancy_fit": 2.0, "mesh": 1.5, "total": 3.5},
        "peak_rss_mb": 812.0,
        "versions": {"ultron": "0.1.0"},
    }


def test_round_trip_keeps_every_entry(tmp_path: Path):
    data = _schema_one()
    record = RunRecord.from_dict(data)
    assert record.mesh == MeshSummary(10, 16, 12.5, "ras")
    assert record.details == {
        "selection": data["selection"],
        "occupancy_log": [{"step": 0, "loss": 0.7}],
    }
    assert record.field_dataset_match is None and record.total_s == 3.5
    written = record.write(tmp_path)
    text = written.read_text(encoding="utf-8")
    assert text.lstrip("{\n ").startswith('"schema"')  # the schema heads the file
    expected = {k: v for k, v in data.items() if v is not None}
    assert json.loads(text) == expected
    assert RunRecord.read(tmp_path) == record


def test_a_file_written_before_the_schema_is_read():
    old = {"method": "ultron-finetune", "seed": 0, "timings_s": {"fit": 1.0, "write": 0.5}}
    record = RunRecord.from_dict(old)
    assert record.command == "finetune"  # inferred from the method
    assert record.mesh is None and record.device is None and record.label_fraction is None
    assert record.total_s == 1.5  # no "total": the stages' sum
    assert record.schema == RUN_SCHEMA and record.to_dict()["schema"] == RUN_SCHEMA


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"schema": "ultron-run/9"}, "schema"),
        ({"seed": "3"}, "seed"),
        ({"seed": True}, "seed"),
        ({"label_fraction": float("nan")}, "label_fraction"),
        ({"method": None}, "method"),
        ({"timings_s": None}, "timings_s"),
        ({"timings_s": {"total": "slow"}}, "timings_s.total"),
        ({"mesh": {"vertices": 1, "faces": 2}}, "mesh.area_mm2"),
        ({"mesh": [1, 2]}, "mesh"),
        ({"field_cached": "yes"}, "field_cached"),
        ({"device": None}, "device"),
        ({"command": 4}, "command"),
    ],
)
def test_bad_entries_are_named(change: dict, field: str):
    data = _schema_one() | change
    with pytest.raises(UltronInputError, match=rf"run\.json: {field}:"):
        RunRecord.from_dict(data)


def test_unreadable_files_are_named(tmp_path: Path):
    with pytest.raises(UltronInputError, match="file is missing"):
        RunRecord.read(tmp_path)
    (tmp_path / "run.json").write_text("{not json")
    with pytest.raises(UltronInputError, match="not readable JSON"):
        RunRecord.read(tmp_path)
    (tmp_path / "run.json").write_text("[1, 2]")
    with pytest.raises(UltronInputError, match="expected a JSON object"):
        RunRecord.read(tmp_path)
