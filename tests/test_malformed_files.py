"""Malformed files that ultron itself writes (dataset.json, field.json, theta_stats.json,
network.pt), edited by hand or by a hostile tool: each read ends in one UltronInputError naming
the file and the entry, never a traceback."""

from __future__ import annotations

import io
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from ultron.data.dataset import SweepDataset
from ultron.errors import UltronInputError
from ultron.fields.occupancy import OccupancyNetwork, OccupancyNetworkConfig
from ultron.models.fitted import load_field
from ultron.pipeline.model_io import load_network, save_network
from ultron.train import field_preset, fit_field

DEEP = "[" * 100_000 + "]" * 100_000


@pytest.fixture(scope="module")
def field_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from conftest import build_tiny_dataset

    root = tmp_path_factory.mktemp("field")
    config = field_preset(iterations=2, fit_shape=(8, 8), check_every=2, max_check_frames=1)
    fit_field(build_tiny_dataset(), config, root / "field")
    return root / "field"


def _copy(field_dir: Path, tmp_path: Path) -> Path:
    target = tmp_path / "field"
    target.mkdir()
    for path in field_dir.iterdir():
        (target / path.name).write_bytes(path.read_bytes())
    return target


def _edit_json(path: Path, change: Callable[[dict], None]) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


FIELD_CASES: dict[str, tuple[Callable[[Path], None], str, str]] = {
    "field.json nested 100k deep": (
        lambda f: (f / "field.json").write_text(DEEP),
        "field.json",
        "nested too deeply",
    ),
    "field is a string": (
        lambda f: _edit_json(f / "field.json", lambda m: m.update(field="grid")),
        "field",
        "expected an object",
    ),
    "resolutions is a word": (
        lambda f: _edit_json(
            f / "field.json", lambda m: m["field"]["grid"].update(resolutions="big")
        ),
        "field",
        "",
    ),
    "probe has an unknown entry": (
        lambda f: _edit_json(f / "field.json", lambda m: m["probe"].update(colour="red")),
        "probe",
        "malformed",
    ),
    "theta_stats mean is a word": (
        lambda f: _edit_json(f / "theta_stats.json", lambda m: m.update(mean="x")),
        "theta_stats.json.mean",
        "finite numbers",
    ),
    "theta_stats nested 100k deep": (
        lambda f: (f / "theta_stats.json").write_text(DEEP),
        "theta_stats.json",
        "nested too deeply",
    ),
}


@pytest.mark.parametrize("case", FIELD_CASES)
def test_a_malformed_field_dir_is_one_error_naming_file_and_entry(
    case: str, field_dir: Path, tmp_path: Path
) -> None:
    edit, field, hint = FIELD_CASES[case]
    copy = _copy(field_dir, tmp_path)
    load_field(copy)  # the untouched copy loads
    edit(copy)
    with pytest.raises(UltronInputError) as caught:
        load_field(copy)
    assert caught.value.field.startswith(field), caught.value
    assert caught.value.where.endswith((".json",)), caught.value
    assert hint in caught.value.problem and "\n" not in str(caught.value)


def test_a_dataset_json_nested_too_deeply_is_one_error(tiny_dataset_dir: Path) -> None:
    (tiny_dataset_dir / "dataset.json").write_text(DEEP)
    with pytest.raises(UltronInputError, match=r"dataset\.json: JSON nested too deeply"):
        SweepDataset.load(tiny_dataset_dir)


def _network_payload(tmp_path: Path) -> dict:
    network = OccupancyNetwork(OccupancyNetworkConfig(in_dim=3, width=8, depth=2, skip_at=1))
    save_network(tmp_path, network, {"loss": "ultron"})
    return torch.load(tmp_path / "network.pt", weights_only=True)


NETWORK_CASES: dict[str, tuple[Callable[[dict], None], str]] = {
    "unknown config key": (lambda p: p["config"].update(colour="red"), "config"),
    "config is a string": (lambda p: p.update(config="big"), "config"),
    "no state_dict": (lambda p: p.pop("state_dict"), "state_dict"),
    "meta is a string": (lambda p: p.update(meta="x"), "meta"),
    "weights of another shape": (
        lambda p: p["state_dict"].update({k: torch.zeros(2) for k in p["state_dict"]}),
        "state_dict",
    ),
}


@pytest.mark.parametrize("case", NETWORK_CASES)
def test_a_malformed_network_is_one_error_naming_the_entry(case: str, tmp_path: Path) -> None:
    edit, field = NETWORK_CASES[case]
    payload = _network_payload(tmp_path)
    load_network(tmp_path)  # the untouched file loads
    edit(payload)
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    (tmp_path / "network.pt").write_bytes(buffer.getvalue())
    with pytest.raises(UltronInputError) as caught:
        load_network(tmp_path)
    assert caught.value.field.startswith(field), caught.value
    assert caught.value.where.endswith("network.pt") and "\n" not in str(caught.value)


def test_a_field_whose_weights_are_nan_is_refused_before_rendering(
    field_dir: Path, tmp_path: Path
) -> None:
    copy = _copy(field_dir, tmp_path)
    state = torch.load(copy / "checkpoint.pt", weights_only=True)
    name = next(k for k, v in state["model"].items() if v.is_floating_point())
    state["model"][name] = torch.full_like(state["model"][name], float("nan"))
    torch.save(state, copy / "checkpoint.pt")
    with pytest.raises(UltronInputError) as caught:
        load_field(copy)
    assert caught.value.field == "model" and name in caught.value.problem


def test_a_network_whose_weights_are_nan_is_refused(tmp_path: Path) -> None:
    payload = _network_payload(tmp_path)
    name = next(iter(payload["state_dict"]))
    payload["state_dict"][name] = payload["state_dict"][name] * float("inf")
    torch.save(payload, tmp_path / "network.pt")
    with pytest.raises(UltronInputError, match="NaN or inf"):
        load_network(tmp_path)


def _png_folder(tmp_path: Path, images: list) -> Path:
    folder = tmp_path / "images"
    folder.mkdir(parents=True)
    for i, image in enumerate(images):
        image.save(folder / f"{i}.png")
    return folder


def test_a_palette_png_reads_as_its_grey_levels_not_its_indices(tmp_path: Path) -> None:
    from PIL import Image

    from ultron.data.importers import read_png_frames

    grey = np.arange(48, dtype=np.uint8).reshape(6, 8) * 5
    palette = Image.fromarray(grey, mode="L").convert("P", palette=Image.ADAPTIVE, colors=48)
    assert not np.array_equal(np.asarray(palette), grey)  # indices differ from the levels
    frames = read_png_frames(_png_folder(tmp_path, [palette]))
    assert np.array_equal(frames[0], grey)
    coloured = Image.fromarray(np.stack([grey, grey // 2, grey], axis=-1)).convert("P")
    with pytest.raises(UltronInputError, match="colour PNG"):
        read_png_frames(_png_folder(tmp_path / "c", [coloured]))


def test_a_png_declaring_a_huge_frame_is_refused_before_decoding(tmp_path: Path) -> None:
    from PIL import Image

    from ultron.data.importers import MAX_FRAME_PIXELS, read_png_frames

    side = int(np.sqrt(MAX_FRAME_PIXELS)) + 16
    folder = tmp_path / "images"
    folder.mkdir()
    Image.new("L", (side, side)).save(folder / "0.png")  # compresses to a few kB
    assert (folder / "0.png").stat().st_size < 200_000
    with pytest.raises(UltronInputError, match="declares"):
        read_png_frames(folder)


def test_an_ultranerf_folder_with_both_images_npy_and_pngs_is_ambiguous(tmp_path: Path) -> None:
    from PIL import Image

    from ultron.data.importers import read_ultranerf

    src = tmp_path / "un"
    src.mkdir()
    _png_folder(src, [Image.fromarray(np.zeros((6, 4), np.uint8))])
    np.save(src / "images.npy", np.zeros((1, 6, 4), np.uint8))
    np.save(src / "poses.npy", np.eye(4)[None])
    with pytest.raises(UltronInputError, match=r"both images\.npy and images"):
        read_ultranerf(src, 8.0, 12.0)


def test_a_forged_npy_header_is_refused_before_allocating(tmp_path: Path) -> None:
    from ultron.data.validation import load_npy

    path = tmp_path / "images.npy"
    np.save(path, np.zeros((2, 2), np.uint8))
    header = path.read_bytes()
    path.write_bytes(header.replace(b"(2, 2)", b"(%d,)" % 10**18))  # 10¹⁸ bytes in 134
    with pytest.raises(UltronInputError, match="declares"):
        load_npy(path, "images")


def _sequence(tmp_path: Path, **changes) -> Path:
    from plus_synthetic import recording, write_mha

    return write_mha(tmp_path / "rec.igs.mha", recording(n=3, height=12, width=16), **changes)


@pytest.mark.parametrize(
    ("changes", "hint"),
    [
        ({"payload_edit": lambda b: b + b"\0" * 7}, "longer than DimSize"),
        ({"payload_edit": lambda b: b[:-5]}, "truncated payload"),
        (
            {"edit": lambda h: [(k, "100000 100000 3" if k == "DimSize" else v) for k, v in h]},
            "truncated payload",
        ),
        (
            {
                "compressed": True,
                "edit": lambda h: [(k, "100000 100000 30" if k == "DimSize" else v) for k, v in h],
            },
            "GiB, more than",
        ),
    ],
)
def test_a_raw_payload_that_does_not_match_dimsize_is_refused(
    tmp_path: Path, changes: dict, hint: str
) -> None:
    from ultron.data.plus import read_sequence

    assert read_sequence(_sequence(tmp_path)).pixels.shape == (3, 12, 16)
    with pytest.raises(UltronInputError) as caught:
        read_sequence(_sequence(tmp_path, **changes))
    assert hint in caught.value.problem and caught.value.where.endswith("rec.igs.mha")


def test_a_ply_whose_face_names_a_missing_vertex_is_refused(tmp_path: Path) -> None:
    from ultron.mesh.export import load_mesh

    head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    head += "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
    path = tmp_path / "m.ply"
    path.write_text(head + "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    assert len(load_mesh(path).faces) == 1
    path.write_text(head + "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")
    with pytest.raises(UltronInputError, match="index out of range"):
        load_mesh(path)


def test_a_pose_beyond_any_tracker_is_refused_without_overflow_warnings(
    tiny_dataset_dir: Path,
) -> None:
    import warnings

    poses_path = tiny_dataset_dir / "row" / "poses.npy"
    poses = np.load(poses_path)
    poses[1, 0, 3] = 1e300
    np.save(poses_path, poses)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(UltronInputError, match="pose 1 translates by 1e"):
            SweepDataset.load(tiny_dataset_dir)
