"""Echo support (:mod:`ultron.mesh.echo_support`) and its use in the observed-surface crop."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from ultron.data.auto_labels import frame_evidence
from ultron.data.dataset import ProbeGeometry
from ultron.errors import UltronInputError
from ultron.mesh.echo_support import EchoSupportConfig, depth_relative_shadow, echo_support_map
from ultron.mesh.observed import ObservedSurfaceConfig, observe_surface, observed_points

#: 100 rows × 80 columns of 0.5 mm: a 40 mm wide, 50 mm deep probe (as test_auto_labels).
PROBE = ProbeGeometry(width_mm=40.0, depth_mm=50.0, height_px=100, width_px=80)
LINE_ROW = 40
#: The default shadow onset in rows of 0.5 mm.
ONSET_ROWS = round(EchoSupportConfig().shadow_onset_mm / PROBE.axial_spacing_mm)


def _frame(line: bool, shadow: bool, seed: int = 0, columns: slice = slice(None)) -> np.ndarray:
    """Rayleigh speckle (mean ≈ 90 grey levels); with ``line`` a bright 2-pixel line at
    ``LINE_ROW``, with ``shadow`` weak noise under that row, in ``columns``."""
    rng = np.random.default_rng(seed)
    image = np.clip(rng.rayleigh(72.0, size=PROBE.image_shape), 0, 255)
    if line:
        image[LINE_ROW : LINE_ROW + 2, columns] = 250.0
    if shadow:
        below = image[LINE_ROW + 2 :, columns]
        image[LINE_ROW + 2 :, columns] = rng.uniform(0, 8, size=below.shape)
    return image.astype(np.uint8)


def test_a_bone_echo_is_supported_within_the_window_and_nothing_else():
    # line and shadow span the frame (a long bone along its axis): the shadow is as dark as
    # its depth's level, and the echo shows bone through the shadow directly beneath it
    support = echo_support_map(_frame(line=True, shadow=True), PROBE)
    window = 2  # 1 mm of 0.5 mm rows
    assert support[LINE_ROW].all() and support[LINE_ROW + 1].all()
    # lit speckle more than the shadow onset plus the window above: not bone
    assert not support[: LINE_ROW - ONSET_ROWS - window - 1].any()
    # deep in the shadow (beyond the window under the echo): the shadow itself shows nothing
    assert not support[LINE_ROW + 2 + window + 1 :].any()


@pytest.mark.parametrize("onset_mm", [2.0, 4.0])
def test_a_shadow_alone_supports_the_tissue_above_its_onset(onset_mm: float):
    # a dim interface under the left half: no echo, but a shadow beside lit tissue
    image = _frame(line=False, shadow=True, columns=slice(0, 40))
    config = EchoSupportConfig(depth_window_mm=0.0, shadow_onset_mm=onset_mm)
    support = echo_support_map(image, PROBE, config)[:, :36]  # clear of the smoothed edge
    onset, reach = LINE_ROW + 2, round(onset_mm / PROBE.axial_spacing_mm)
    rows = np.flatnonzero(support.all(axis=1))
    assert rows.max() < onset  # the shadow itself is not supported
    assert rows.min() >= onset - reach  # at most onset_mm above the onset …
    assert rows.min() <= onset - reach + 2  # … and most of those millimetres


def _faded_frame(scale_rows: float = 15.0) -> np.ndarray:
    """Rayleigh speckle whose gain falls as exp(−row/``scale_rows``) across the whole frame:
    its echoes fade below the shadow level (by row ≈ 20 at 15) with nothing in the way."""
    rng = np.random.default_rng(3)
    gain = np.exp(-np.arange(PROBE.height_px) / scale_rows)[:, None]
    return np.clip(rng.rayleigh(72.0, size=PROBE.image_shape) * gain, 0, 255).astype(np.uint8)


def test_a_fade_across_the_frame_is_no_shadow():
    bottom = PROBE.height_px - ONSET_ROWS - 2  # the frame's end: see below
    # under the top rows (where bright speckle over the fade scores as an echo): no row of
    # the fade is taken for bone …
    faded = echo_support_map(_faded_frame(), PROBE)
    assert faded[10:bottom].mean(axis=1).max() < 0.1
    # … but without the test against the depth's lit level the fade's floor reads as a
    # shadow onset in every column, and the tissue just above it as bone
    old = EchoSupportConfig(shadow_depth_ratio=math.inf)
    assert echo_support_map(_faded_frame(), PROBE, old)[10:bottom].mean(axis=1).max() > 0.9


def test_an_echo_over_a_fade_casts_no_shadow():
    # a bright line 8 mm deep over a slow fade whose floor lies ≈ 10 mm under it: an echo
    # the detector scores (nothing below outshines it) but that casts no shadow of its own
    image = _faded_frame(scale_rows=40.0)
    image[16:18] = 250
    assert not echo_support_map(image, PROBE)[16:18].any()
    old = EchoSupportConfig(shadow_depth_ratio=math.inf)  # the fade's floor read as its shadow
    assert echo_support_map(image, PROBE, old)[16:18].all()


def test_speckle_without_bone_and_a_blank_frame_are_unsupported():
    support = echo_support_map(_frame(line=True, shadow=False), PROBE)
    bottom = PROBE.height_px - ONSET_ROWS - 2  # the last onset and the 1 mm window: see below
    assert support[:bottom].mean() < 0.01
    assert not echo_support_map(np.zeros(PROBE.image_shape, np.uint8), PROBE).any()


def test_the_frames_last_millimetres_show_an_echo_not_plain_speckle():
    end = PROBE.height_px - ONSET_ROWS  # within the onset of the last row
    speckle = _frame(line=False, shadow=False)
    # plain speckle over the frame's end shows no bone …
    assert echo_support_map(speckle, PROBE)[end:].mean() < 0.02
    # … but did while the frame's end counted as an onset for any lit pixel
    old = echo_support_map(speckle, PROBE, EchoSupportConfig(frame_end_echo=None))
    assert old[end:].all()
    assert not old[: end - 2 - 1].any()
    # a deep wall's echo at the bottom of the frame, 2.5 × the speckle's median once smoothed
    image = speckle.copy()
    image[end + 1 : end + 3, 20:40] = 250
    config = EchoSupportConfig(depth_window_mm=0.0, frame_end_echo=2.0)
    support = echo_support_map(image, PROBE, config)
    assert support[end + 1 : end + 3, 22:38].all()  # no frame can show whether a shadow follows
    assert support[end:, 45:].mean() < 0.02
    assert not support[: end - 1].any()


def test_the_frame_end_echo_is_relative_to_its_rows_level():
    # a deep wall in a frame whose echoes fade with depth: dimmer than the speckle near the
    # probe, bright against the speckle at its own depth — bone by default (m = 3); a factor
    # above its contrast drops it
    image = _faded_frame(scale_rows=60.0)
    end = PROBE.height_px - ONSET_ROWS
    wall = 3 * int(image[end + 1 : end + 3].max())
    assert wall < image[:10].max()
    image[end + 1 : end + 3, 20:40] = wall
    for m, shown in ((EchoSupportConfig().frame_end_echo, True), (20.0, False)):
        config = EchoSupportConfig(depth_window_mm=0.0, frame_end_echo=m)
        assert echo_support_map(image, PROBE, config)[end + 1 : end + 3, 22:38].all() == shown


def test_bad_inputs_name_the_argument():
    with pytest.raises(UltronInputError, match="image"):
        echo_support_map(np.zeros((10, 10), np.uint8), PROBE)
    with pytest.raises(UltronInputError, match="depth_window_mm"):
        EchoSupportConfig(depth_window_mm=-1.0)
    evidence = frame_evidence(_faded_frame(), PROBE, EchoSupportConfig().detector)
    with pytest.raises(UltronInputError, match="config"):
        depth_relative_shadow(evidence, PROBE, {"shadow_depth_ratio": 0.3})  # type: ignore[arg-type]
    small = ProbeGeometry(width_mm=40.0, depth_mm=25.0, height_px=50, width_px=80)
    with pytest.raises(UltronInputError, match="evidence"):
        depth_relative_shadow(evidence, small, EchoSupportConfig())
    for ratio in (0.0, -1.0, math.nan):
        with pytest.raises(UltronInputError, match="shadow_depth_ratio"):
            EchoSupportConfig(shadow_depth_ratio=ratio)
    with pytest.raises(UltronInputError, match="detector"):
        EchoSupportConfig(detector={"gap_mm": 1.0})  # type: ignore[arg-type]
    for factor in (-0.5, math.inf, math.nan, True, "1"):
        with pytest.raises(UltronInputError, match="frame_end_echo"):
            EchoSupportConfig(frame_end_echo=factor)  # type: ignore[arg-type]


def _plate_seen_from_above(depth_mm: float):
    """A 20 mm plate, 0.4 mm across the elevational slab, facing up at ``depth_mm`` under a
    probe looking down (−z), the probe's image plane x–z, its origin at z = 0; the pose and
    T ≡ 1."""
    plate = trimesh.creation.box((20.0, 0.4, 0.1))
    plate.apply_translation((0.0, 0.0, -depth_mm))
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # probe +y = world −z
    t_maps = np.ones((1, *PROBE.image_shape), np.float32)
    return plate, pose[None], t_maps


def test_observed_points_need_the_same_frames_support():
    plate, poses, t_maps = _plate_seen_from_above(depth_mm=LINE_ROW * 0.5)
    top = np.asarray(plate.vertices)[:, 2] > -LINE_ROW * 0.5
    args = (plate.vertices, plate.vertex_normals, poses, PROBE, t_maps, 0.5)
    assert observed_points(*args)[top].all()
    nothing = np.zeros_like(t_maps, dtype=bool)
    assert not observed_points(*args, support=nothing).any()
    echo = np.zeros_like(nothing)
    echo[0, LINE_ROW - 1 : LINE_ROW + 2] = True  # the plate's rows, ± a row
    seen = observed_points(*args, support=echo)
    assert seen[top].all() and not seen[~top].any()
    with pytest.raises(UltronInputError, match="support"):
        observed_points(*args, support=echo[0])


def test_observe_surface_records_the_echo_support():
    plate, poses, t_maps = _plate_seen_from_above(depth_mm=LINE_ROW * 0.5)
    config = ObservedSurfaceConfig()
    plain = observe_surface(plate, poses, PROBE, t_maps, 0.5, config, "field")
    assert plain.info["echo_support"] is False and plain.observed.any()
    nothing = np.zeros_like(t_maps, dtype=bool)
    cropped = observe_surface(plate, poses, PROBE, t_maps, 0.5, config, "field", nothing)
    assert cropped.info["echo_support"] is True
    assert not cropped.observed.any() and cropped.info["surface_fallback"] == "all"


def test_the_frame_that_shows_bone_need_not_be_the_one_that_observed():
    plate, poses, t_maps = _plate_seen_from_above(depth_mm=LINE_ROW * 0.5)
    top = np.asarray(plate.vertices)[:, 2] > -LINE_ROW * 0.5
    two_poses = np.concatenate([poses, poses])
    lit_then_dark = np.concatenate([t_maps, np.zeros_like(t_maps)])  # frame 1: T = 0
    echo_in_1 = np.zeros_like(lit_then_dark, dtype=bool)
    echo_in_1[1, LINE_ROW - 1 : LINE_ROW + 2] = True  # only the unlit frame shows the echo
    args = (plate.vertices, plate.vertex_normals, two_poses, PROBE)
    seen = observed_points(*args, lit_then_dark, 0.5, support=echo_in_1)
    assert seen[top].all()
    # shown as bone but lit in no frame: not observed
    dark = np.zeros_like(lit_then_dark)
    assert not observed_points(*args, dark, 0.5, support=echo_in_1).any()


def test_the_labelled_surface_is_observed_within_the_support_distance():
    plate, poses, t_maps = _plate_seen_from_above(depth_mm=LINE_ROW * 0.5)
    dark = np.zeros_like(t_maps)  # no beam reaches the plate: no frame observes it
    vertices = np.asarray(plate.vertices)
    corner = vertices[np.argmax(vertices[:, 0] + vertices[:, 1] + vertices[:, 2])]
    label = (corner + np.array([0.0, 0.0, 0.7]))[None]  # 0.7 mm above one top corner
    near = np.linalg.norm(vertices - label, axis=1) <= 1.0  # 0.7, 0.81, 0.8, 0.89 mm: 4 corners
    assert near.sum() == 4
    config = ObservedSurfaceConfig(label_support_mm=1.0)
    seen = observe_surface(plate, poses, PROBE, dark, 0.5, config, "field", None, label)
    assert (seen.observed == near).all() and seen.info["label_supported_vertices"] == 4
    tight = observe_surface(
        plate, poses, PROBE, dark, 0.5, ObservedSurfaceConfig(label_support_mm=0.75), "field",
        None, label,
    )  # fmt: skip
    assert tight.observed.sum() == 1
    off = ObservedSurfaceConfig(label_support_mm=0.0)
    assert not observe_surface(
        plate, poses, PROBE, dark, 0.5, off, "field", None, label
    ).observed.any()
    unlabelled = observe_surface(plate, poses, PROBE, dark, 0.5, config, "field")
    assert not unlabelled.observed.any() and "label_supported_vertices" not in unlabelled.info
    assert unlabelled.info["surface"]["label_support_mm"] == 0  # what was applied
    assert unlabelled.info["surface"]["label_bridges"] is False
    assert seen.info["surface"]["label_support_mm"] == 1.0
    lit = observe_surface(plate, poses, PROBE, t_maps, 0.5, config, "field", None, label)
    top = vertices[:, 2] > -LINE_ROW * 0.5  # what the lit frame observes (facing the probe)
    assert (lit.observed == (top | near)).all()
    assert lit.info["label_supported_vertices"] == np.count_nonzero(near & ~top) == 2


@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf"), True, "1"])
def test_a_bad_label_support_distance_names_it(value):
    with pytest.raises(UltronInputError, match="label_support_mm"):
        ObservedSurfaceConfig(label_support_mm=value)
