"""The method registry: one interface, one list of methods that every caller reads."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from ultron.cli.main import app
from ultron.errors import UltronInputError
from ultron.mesh.compounding import CompoundingConfig
from ultron.mesh.extract import ExtractionConfig
from ultron.mesh.observed import OBSERVED_EXTRACTION
from ultron.mesh.occupancy_mesh import MeshingConfig
from ultron.methods.catalog import FIELD_METHODS, METHOD_NAMES
from ultron.methods.compounding_method import CompoundingMethodConfig
from ultron.methods.on_method import ONConfig
from ultron.methods.registry import METHODS, MethodInputs, get_method
from ultron.methods.rocosdf import RoCoSDFConfig
from ultron.methods.ultron_method import UltronConfig
from ultron.pipeline.run import ReconstructionRequest, run_method
from ultron.timing import StageTimer

NAMES = ("ultron", "ultron-noloss", "compounding", "on", "rocosdf", "unsr-row", "unsr-col")


def test_registry_holds_every_method_once():
    assert tuple(METHODS) == NAMES
    assert FIELD_METHODS == ("ultron", "ultron-noloss")
    for name, method in METHODS.items():
        assert method.name == name and get_method(name) is method
        assert callable(method.fit)
    configs = {name: METHODS[name].config_class for name in NAMES}
    assert configs["ultron"] is UltronConfig and configs["compounding"] is CompoundingMethodConfig
    assert configs["on"] is ONConfig and configs["unsr-col"] is RoCoSDFConfig
    # compounding meshes the labelled bone's box (its own memory check), RoCoSDF / UNSR theirs
    off_scan = ["compounding", "rocosdf", "unsr-row", "unsr-col"]
    assert [n for n in NAMES if not METHODS[n].scan_grid] == off_scan
    views = {n: METHODS[n].views for n in ("rocosdf", "unsr-row", "unsr-col")}
    assert views == {"rocosdf": ("row", "column"), "unsr-row": ("row",), "unsr-col": ("column",)}
    assert all(METHODS[n].needs_field is (n in FIELD_METHODS) for n in NAMES)


def test_registry_is_read_only():
    with pytest.raises(TypeError):
        METHODS["magic"] = METHODS["on"]  # type: ignore[index]


def test_unknown_method_names_the_argument():
    with pytest.raises(UltronInputError, match=r"method: expected one of \('ultron'"):
        get_method("magic")
    with pytest.raises(UltronInputError, match="method"):
        ReconstructionRequest(method="magic")


@pytest.mark.parametrize("name", FIELD_METHODS)
def test_a_field_method_without_a_field_is_a_clear_error(name, tiny_dataset):
    request = ReconstructionRequest(method=name)
    with pytest.raises(UltronInputError, match="needs a fitted acoustic field"):
        run_method(tiny_dataset, request, None, StageTimer())
    with pytest.raises(UltronInputError, match="needs a fitted acoustic field"):
        METHODS[name].fit(tiny_dataset, MethodInputs(request.method_config, StageTimer()))


def test_reconstruct_help_lists_every_registered_method():
    result = CliRunner().invoke(app, ["reconstruct", "--help"], terminal_width=300)
    assert result.exit_code == 0
    text = " ".join(result.output.replace("│", " ").split())
    *first, last = METHODS
    assert f"{', '.join(first)} or {last}." in text


def test_the_catalog_lists_the_registry_without_loading_it():
    assert METHOD_NAMES == tuple(METHODS)
    code = "import sys, ultron.methods.catalog; print('torch' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.stdout.strip() == "False", result.stderr


class _Stages:
    """Every method's settings, as a preset holds them (registry.StageSettings)."""

    ultron = UltronConfig(voxel_mm=0.7)
    on = replace(ONConfig(), meshing=replace(ONConfig().meshing, voxel_mm=0.9))
    rocosdf_preset = "paper"


def test_on_records_only_the_meshing_it_uses():
    """ON's meshing settings are a MeshingConfig — the four fields mesh_occupancy reads — not
    an UltronConfig whose loss, crop and echo settings ON never uses; UltrON's mirror its own
    fields, so both mesh the same way by default — except that UltrON, which the observed crop
    trims, meshes every piece, and ON, which has no crop, drops the small ones."""
    on = ONConfig()
    assert isinstance(on.meshing, MeshingConfig)
    assert {f for f in vars(on.meshing)} == {
        "voxel_mm",
        "coarse_factor",
        "chunk_points",
        "extraction",
    }
    ultron = UltronConfig(voxel_mm=0.7, coarse_factor=4, chunk_points=1000)
    assert ultron.meshing == MeshingConfig(0.7, 4, 1000, ultron.surface_extraction)
    assert UltronConfig().meshing == replace(on.meshing, extraction=OBSERVED_EXTRACTION)
    assert on.meshing.extraction == ExtractionConfig()
    assert OBSERVED_EXTRACTION.min_component_fraction < ExtractionConfig().min_component_fraction


@pytest.mark.parametrize(
    ("changes", "argument"),
    [({"voxel_mm": 0.0}, "voxel_mm"), ({"coarse_factor": 0}, "coarse_factor"),
     ({"chunk_points": 0}, "chunk_points"), ({"chunk_points": True}, "chunk_points")],
)  # fmt: skip
def test_meshing_settings_refuse_bad_values(changes, argument):
    with pytest.raises(UltronInputError, match=argument):
        MeshingConfig(**changes)
    with pytest.raises(UltronInputError, match=argument):
        UltronConfig(**changes)


def test_each_method_owns_its_settings_meshing_voxel_and_loss():
    configs = {name: METHODS[name].config_of(_Stages) for name in METHODS}
    for name, config in configs.items():
        assert isinstance(config, METHODS[name].config_class), name
    assert configs["ultron"] is _Stages.ultron and configs["on"] is _Stages.on
    assert configs["rocosdf"] == RoCoSDFConfig.preset("paper")
    # compounding meshes with UltrON's extraction and observed crop, at its own voxel
    assert configs["compounding"].observed is _Stages.ultron.observed
    assert configs["compounding"].extraction is _Stages.ultron.extraction
    configs["compounding"] = CompoundingMethodConfig(CompoundingConfig(voxel_mm=0.3))
    voxels = {name: METHODS[name].meshing_voxel(configs[name]) for name in METHODS}
    assert voxels == {
        "ultron": 0.7, "ultron-noloss": 0.7, "compounding": 0.3, "on": 0.9,
        "rocosdf": None, "unsr-row": None, "unsr-col": None,
    }  # fmt: skip
    assert METHODS["ultron"].visibility(configs["ultron"]) is _Stages.ultron.visibility
    assert [n for n in METHODS if METHODS[n].visibility(configs[n]) is not None] == list(
        FIELD_METHODS
    )
    assert {n: METHODS[n].loss for n in FIELD_METHODS} == {
        "ultron": "ultron",
        "ultron-noloss": "bce",
    }


def test_benchmark_plans_fields_from_the_registry(tmp_path):
    from ultron.benchmark import plan_benchmark, quick_config
    from ultron.benchmark.plan import ReconstructJob

    plan = plan_benchmark(quick_config(generalisation=False), tmp_path)
    jobs = [t.job for t in plan.tasks.values() if isinstance(t.job, ReconstructJob)]
    assert jobs
    for job in jobs:
        method = METHODS[job.request.method]
        assert (job.field_dir is not None) == method.needs_field
        # each cell's request carries its own method's settings, the benchmark's preset's
        assert type(job.request.method_config) is method.config_class
    ultron = next(j for j in jobs if j.request.method == "ultron").request.method_config
    assert ultron.occupancy.iters == quick_config().ultron.occupancy.iters


def test_cli_unknown_method_is_one_line_naming_the_option(tmp_path):
    out = tmp_path / "o"
    result = CliRunner().invoke(
        app, ["reconstruct", str(tmp_path), "--out", str(out), "--method", "magic"]
    )
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "--method" in lines[0] and "unsr-col" in lines[0]
    assert not out.exists()


@pytest.mark.parametrize("fraction", [True, 0, 1.5, float("nan"), "0.1", None])
def test_every_label_fraction_check_refuses_the_same_values(fraction, tiny_dataset):
    from ultron.data.labels import select_label_frames
    from ultron.methods.finetune import FinetuneConfig

    for build in (
        lambda: ReconstructionRequest("ultron", label_fraction=fraction),
        lambda: FinetuneConfig(label_fraction=fraction),
        lambda: select_label_frames(tiny_dataset, fraction, 0),
    ):
        with pytest.raises(UltronInputError, match=r"label_fraction: expected a value in \(0, 1\]"):
            build()


def test_a_label_fraction_of_numpy_float_or_one_is_taken():
    assert ReconstructionRequest("ultron", label_fraction=np.float32(0.05)).label_fraction > 0
    assert ReconstructionRequest("ultron", label_fraction=1).label_fraction == 1
