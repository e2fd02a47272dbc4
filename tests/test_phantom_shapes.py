"""Vertebra phantoms: SDF signs and distances, bounds, reference mesh, tissue formulas."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ultron.errors import UltronInputError
from ultron.phantom import PHANTOMS, get_phantom
from ultron.phantom.primitives import SegmentBox, smooth_union
from ultron.phantom.tissue import (
    CORTICAL_BONE,
    GEL_PULP,
    incidence_factor,
    intensity_reflection,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_phantom_names():
    assert set(PHANTOMS) == {"L2", "L3", "L3b", "L4"}
    assert get_phantom("L3").name == "L3"


def test_condyle_is_a_short_long_bone_for_the_benchmark():
    from ultron.phantom.shapes import BENCHMARK_PHANTOMS

    condyle = get_phantom("condyle")
    assert BENCHMARK_PHANTOMS == ("L2", "L3", "L3b", "L4", "condyle")
    pts = torch.tensor(
        [
            [0.0, 0.0, 0.0],  # shaft axis at mid-shaft: 12 mm from the surface
            [0.0, -12.0, 0.0],  # the shaft's posterior surface, which faces the probe
            [14.0, 0.0, -34.0],  # a condyle's centre (z = -25 - 18/2)
            [0.0, 0.0, 38.0],  # inside the rounded cap (centre z = 25 + 6, radius 12)
            [30.0, 0.0, 0.0],  # lateral of the shaft
            [0.0, 0.0, 60.0],  # beyond the cap
        ],
        dtype=torch.float64,
    )
    d = condyle.sdf(pts)
    # the smooth union of the two overlapping shaft segments adds at most blend / 4 = 0.625 mm
    assert d[0].item() == pytest.approx(-12.0, abs=0.7)
    assert abs(d[1].item()) < 0.7
    assert d[2].item() < -12.0
    assert d[3].item() < -4.0
    assert d[4].item() == pytest.approx(18.0, abs=0.7)
    assert d[5].item() > 10.0
    lo, hi = condyle.bounds_mm.numpy()
    # 2 × (14 + 14) = 56 mm wide at the condyles; 18·1.5 + 50 + 12·1.5 = 95 mm long; the
    # shaft 24 mm thick
    assert hi[0] - lo[0] == pytest.approx(56.0, abs=1.0)
    assert hi[2] - lo[2] == pytest.approx(95.0, abs=1.0)
    assert hi[1] - lo[1] == pytest.approx(32.0, abs=1.0)  # the condyles' 2 × 16 mm


def test_unknown_phantom_is_a_clear_error():
    with pytest.raises(UltronInputError, match=r"phantom.*'L9'.*L2"):
        get_phantom("L9")


def test_sdf_hand_placed_points_l3():
    ph = get_phantom("L3")
    pts = torch.tensor(
        [
            [0.0, 0.0, 0.0],  # body centre: nearest surface is an end plate, 12.5 mm away
            [0.0, 0.0, 14.5],  # 2 mm above the cranial end plate
            [0.0, 14.25, 0.0],  # anterior wall at mid-height (waist: 15·0.95)
            [0.0, -23.5, 0.0],  # middle of the spinal canal: no bone
            [0.0, -90.0, 0.0],  # in the gel, posterior of the spinous process
            [60.0, 0.0, 0.0],  # lateral of the transverse processes
        ],
        dtype=torch.float64,
    )
    d = ph.sdf(pts)
    assert d[0].item() == pytest.approx(-12.5, abs=0.05)
    assert d[1].item() == pytest.approx(2.0, abs=0.05)
    assert abs(d[2].item()) < 0.05
    assert d[3].item() > 3.0
    assert 15.0 < d[4].item() < 35.0
    assert d[5].item() > 10.0


def test_segment_box_is_an_exact_distance():
    box = SegmentBox((0, 0, 0), (10, 0, 0), (0, 0, 1), half_v=2.0, half_w=1.0, radius_mm=0.5)
    pts = torch.tensor(
        [[5.0, 0.0, 0.0], [5.0, 0.0, 3.0], [13.0, 0.0, 0.0], [5.0, 4.0, 0.0]], dtype=torch.float64
    )
    # local axes: u = x (half 5), v = z (half 2), w = u × v = −y (half 1)
    expected = torch.tensor([-1.0, 1.0, 3.0, 3.0], dtype=torch.float64)
    torch.testing.assert_close(box.sdf(pts), expected)


def test_smooth_union_is_min_far_apart_and_below_min_when_close():
    a = torch.tensor([0.0, 1.0, 0.5])
    b = torch.tensor([5.0, -3.0, 0.5])
    u = smooth_union(a, b, 2.0)
    assert u[0].item() == 0.0 and u[1].item() == -3.0
    assert u[2].item() == pytest.approx(0.5 - 2.0 / 4)  # equal inputs: min − k/4


def test_sdf_is_a_distance_near_the_surface():
    ph = get_phantom("L3")
    gen = torch.Generator().manual_seed(0)
    box = ph.bounds_mm
    pts = box[0] + (box[1] - box[0]) * torch.rand((4000, 3), generator=gen, dtype=torch.float64)
    pts.requires_grad_(True)
    d = ph.sdf(pts)
    (grad,) = torch.autograd.grad(d.sum(), pts)
    near = d.detach().abs() < 2.0
    assert near.sum() > 100
    norm = grad[near].norm(dim=-1)
    # A (near-)distance field: unit gradient and Newton projection lands on the surface.
    assert (norm - 1).abs().median() < 0.02
    projected = pts.detach()[near] - d.detach()[near, None] * grad[near] / norm[:, None]
    assert ph.sdf(projected).abs().median() < 0.02


def test_level_dependent_sizes():
    widths = {}
    for name in ("L2", "L3", "L4"):
        ph = get_phantom(name)
        widths[name] = ph.shape.body_width_mm
        box = ph.bounds_mm.numpy()
        # Transverse processes tip to tip 70–85 mm; posterior elements reach 60–70 mm behind
        # the body centre; anterior wall at about half the body depth.
        assert 70.0 < box[1, 0] - box[0, 0] < 85.0
        assert -70.0 < box[0, 1] < -58.0
        assert box[1, 1] == pytest.approx(ph.shape.body_depth_mm / 2, abs=0.5)
    assert widths["L2"] < widths["L3"] < widths["L4"]
    l3 = get_phantom("L3").shape
    assert (l3.body_width_mm, l3.body_depth_mm, l3.body_height_mm) == (45.0, 30.0, 25.0)
    assert l3.spinous_length_mm == 30.0


def test_l3b_is_a_slightly_different_l3():
    gen = torch.Generator().manual_seed(1)
    a, b = get_phantom("L3"), get_phantom("L3b")
    box = a.bounds_mm
    pts = box[0] + (box[1] - box[0]) * torch.rand((20000, 3), generator=gen, dtype=torch.float64)
    diff = (a.sdf(pts) - b.sdf(pts)).abs()
    assert 0.2 < diff.max().item() < 3.0


def test_reference_mesh_watertight_with_expected_extent():
    ph = get_phantom("L3")
    mesh = ph.reference_mesh()
    assert mesh.is_watertight
    assert mesh.volume > 0
    # vertices lie on the analytic surface, the extent matches the bone box
    d = ph.sdf(torch.as_tensor(mesh.vertices[::50]))
    assert d.abs().max().item() < 0.05
    np.testing.assert_allclose(mesh.bounds, ph.bounds_mm.numpy(), atol=0.35)
    # plausible bone volume for a lumbar vertebra (cm³): ≈ 30–60
    assert 30e3 < mesh.volume < 60e3


def test_sdf_volume_matches_analytic_sdf():
    ph = get_phantom("L3")
    volume = ph.sdf_volume()
    gen = torch.Generator().manual_seed(2)
    box = ph.bounds_mm
    pts = box[0] + (box[1] - box[0]) * torch.rand((20000, 3), generator=gen, dtype=torch.float64)
    exact = ph.sdf(pts)
    near = exact.abs() < 1.5
    err = (volume.sample(pts).double() - exact)[near].abs()
    assert err.max().item() < 0.05
    assert ((volume.sample(pts) < 0) == (exact < 0)).float().mean() > 0.999


def test_sdf_rejects_bad_points():
    with pytest.raises(UltronInputError, match="points_mm"):
        get_phantom("L3").sdf(torch.zeros(4, 2))


def test_tissue_formulas_hand_worked():
    # Z = ρc: 1.025·1540 = 1.5785 MRayl; 2.05·3600 = 7.38 MRayl.
    assert GEL_PULP.impedance_mrayl == pytest.approx(1.5785)
    assert CORTICAL_BONE.impedance_mrayl == pytest.approx(7.38)
    assert intensity_reflection(1.5785, 7.38) == pytest.approx((5.8015 / 8.9585) ** 2)
    assert intensity_reflection(1.5, 1.5) == 0.0
    # 20 dB/cm/MHz at 5 MHz = 10 dB/mm
    assert CORTICAL_BONE.attenuation_db_per_mm(5.0) == pytest.approx(10.0)
    g = incidence_factor(torch.tensor([1.0, 0.5, 0.0]), 4.0, 0.25)
    torch.testing.assert_close(g, torch.tensor([1.0, 0.75 * 0.0625 + 0.25 * 0.5, 0.0]))
    with pytest.raises(UltronInputError, match="impedance"):
        intensity_reflection(0.0, 1.0)
