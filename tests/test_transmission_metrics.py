"""Stage-1 diagnostics: an estimated transmission T against the simulator's true one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ultron.errors import UltronInputError
from ultron.metrics.transmission import (
    labelled_transmission_diagnostics,
    roc_auc,
    target_met,
    transmission_diagnostics,
)


def test_roc_auc_hand_worked():
    # positives score 3 and 1, negatives 2 and 0: pairs (3>2, 3>0, 1<2, 1>0) → 3 of 4
    assert roc_auc(np.array([3.0, 1.0, 2.0, 0.0]), np.array([True, True, False, False])) == 0.75
    # a tie counts one half
    assert roc_auc(np.array([1.0, 1.0]), np.array([True, False])) == 0.5
    assert math.isnan(roc_auc(np.array([1.0, 2.0]), np.array([True, True])))
    with pytest.raises(UltronInputError, match="positive"):
        roc_auc(np.array([1.0, 2.0]), np.array([1, 0]))


def test_transmission_diagnostics_hand_worked():
    truth = np.array([1.0, 1.0, 0.95, 0.2, 0.05, 0.0])
    estimate = np.array([0.9, 0.85, 1.0, 0.1, 0.5, 0.2])
    d = transmission_diagnostics(estimate, truth)
    # |errors| = 0.1, 0.15, 0.05, 0.1, 0.45, 0.2 → median (0.1 + 0.15) / 2
    assert d.median_abs_error == pytest.approx(0.125)
    # deep shadow (true < 0.1): 0.05 → 0.5 (not < 0.3), 0.0 → 0.2 (< 0.3): share 1/2
    assert d.n_deep_shadow == 2 and d.deep_shadow_share == 0.5
    assert d.deep_shadow_median == pytest.approx(0.35)
    # shadowed (true < 0.3): estimates 0.1, 0.5, 0.2; lit: 0.9, 0.85, 1.0 → every pair ordered
    assert d.n_shadowed == 3 and d.roc_auc == 1.0
    assert d.lit_median == pytest.approx(0.9)  # true > 0.9: 0.9, 0.85, 1.0
    assert d.meets_targets() == {"median_abs_error": True, "roc_auc": True}
    worse = transmission_diagnostics(np.full(6, 0.5), truth)
    assert worse.roc_auc == 0.5 and worse.meets_targets()["roc_auc"] is False


def test_transmission_diagnostics_leaves_out_nan_and_names_bad_input():
    d = transmission_diagnostics(np.array([np.nan, 1.0]), np.array([0.0, 1.0]))
    assert d.n_pixels == 1 and math.isnan(d.roc_auc)
    assert d.to_dict()["roc_auc"] is None and d.meets_targets()["roc_auc"] is None
    with pytest.raises(UltronInputError, match="estimate"):
        transmission_diagnostics(np.zeros(3), np.zeros(4))
    with pytest.raises(UltronInputError, match="estimate"):
        transmission_diagnostics(np.array([1.5]), np.array([1.0]))
    with pytest.raises(UltronInputError, match="shadow_t"):
        transmission_diagnostics(np.zeros(2), np.zeros(2), shadow_t=1.0)


def test_target_met_compares_each_figure_its_own_way():
    assert target_met("median_abs_error", 0.15) is True
    assert target_met("median_abs_error", 0.151) is False
    assert target_met("roc_auc", 0.9) is True and target_met("roc_auc", 0.89) is False
    assert target_met("roc_auc", None) is None and target_met("roc_auc", math.nan) is None
    with pytest.raises(UltronInputError, match="name"):
        target_met("lit_median", 0.5)


def test_labelled_diagnostics_use_annotated_pixels_only():
    truth = {"a": np.array([[[1.0, 0.0]]]), "b": np.array([[[0.0, 1.0]]])}
    estimate = {"a": np.array([[[1.0, 1.0]]]), "b": np.array([[[0.0, 1.0]]])}
    labels = {"a": np.array([[[0, 255]]], np.uint8), "b": np.array([[[1, 0]]], np.uint8)}
    d = labelled_transmission_diagnostics(estimate, truth, labels)
    assert d.n_pixels == 3 and d.median_abs_error == 0.0 and d.roc_auc == 1.0
    with pytest.raises(UltronInputError, match="sweep 'c'"):
        labelled_transmission_diagnostics({"c": truth["a"]}, truth, labels)


def test_fit_field_cli_writes_and_prints_the_check_on_a_simulated_dataset(tiny_l3, tmp_path):
    """fit-field on a simulated dataset ends with its T against transmission.npy (file and
    one printed line); a dataset without the truth gets neither (test_field_fit)."""
    from typer.testing import CliRunner

    from ultron.cli.main import app
    from ultron.models.field_dir import TRANSMISSION_CHECK, read_transmission_check

    out = tmp_path / "field"
    args = ["fit-field", str(tiny_l3), "--out", str(out), "--iters", "4", "--threads", "1"]
    result = CliRunner().invoke(app, [*args, "--holdout-every", "0"], terminal_width=300)
    assert result.exit_code == 0, result.output
    check = read_transmission_check(out)
    assert check["source"] == "field" and check["n_pixels"] == 2 * 12 * 64 * 48
    printed = "".join(result.output.split())  # rich wraps long lines off a terminal
    assert "".join(str(out / TRANSMISSION_CHECK).split()) in printed
    assert "".join(f"median |T − T_true| {check['median_abs_error']:.3f}".split()) in printed
    assert "".join(f"ROC AUC {check['roc_auc']:.3f}".split()) in printed
