"""Stage 2: the attenuation-compensated loss and occupancy network training."""

from __future__ import annotations

import copy
import math
from dataclasses import replace

import pytest
import torch

from ultron.errors import UltronInputError
from ultron.fields.occupancy import OccupancyNetwork, OccupancyNetworkConfig
from ultron.train.occupancy import (
    OccupancyAnchor,
    OccupancyTrainConfig,
    OccupancyTrainingData,
    attenuation_compensated_bce,
    binary_cross_entropy,
    fit_occupancy,
    label_loss,
    observed_negatives_bce,
    occupancy_in,
    parse_positive_weight,
    positive_class_weight,
)


def test_zero_gradient_where_transmission_is_zero():
    f = torch.tensor([0.2, 0.7, 0.9], dtype=torch.float64, requires_grad=True)
    transmission = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    target = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    attenuation_compensated_bce(f, transmission, target).backward()
    assert f.grad[0] == 0 and f.grad[1] == 0
    assert f.grad[2] != 0


def test_equals_bce_where_transmission_is_one():
    f = torch.tensor([0.1, 0.5, 0.8, 0.99])
    y = torch.tensor([0.0, 1.0, 1.0, 0.0])
    ours = attenuation_compensated_bce(f, torch.ones(4), y)
    torch.testing.assert_close(ours, torch.nn.functional.binary_cross_entropy(f, y))
    torch.testing.assert_close(binary_cross_entropy(f, y), ours)


def test_shadowed_background_costs_nothing():
    # a confident "bone" prediction under a background label in full shadow is free
    loss = attenuation_compensated_bce(
        torch.tensor([0.99]), torch.tensor([0.0]), torch.tensor([0.0])
    )
    assert float(loss) < 1e-5


def test_numerically_safe_at_extremes():
    f = torch.tensor([0.0, 1.0], requires_grad=True)
    loss = attenuation_compensated_bce(f, torch.ones(2), torch.tensor([1.0, 0.0]))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(f.grad).all()


def test_gradcheck_float64():
    f = torch.rand(6, dtype=torch.float64).clamp(0.05, 0.95).requires_grad_()
    transmission = torch.rand(6, dtype=torch.float64).clamp(0.1, 1.0).requires_grad_()
    y = torch.tensor([0, 1, 0, 1, 1, 0], dtype=torch.float64)
    assert torch.autograd.gradcheck(
        lambda a, b: attenuation_compensated_bce(a, b, y), (f, transmission)
    )


def test_shape_mismatch_is_an_error():
    with pytest.raises(UltronInputError, match="shapes differ"):
        attenuation_compensated_bce(torch.zeros(3), torch.zeros(2), torch.zeros(3))


def test_observed_negatives_by_hand():
    # y = 1 counts whatever T; y = 0 counts in full only where T ≥ 0.3; the mean runs over all
    f = torch.tensor([0.8, 0.8, 0.4, 0.4], dtype=torch.float64)
    t = torch.tensor([0.05, 1.0, 0.29, 0.3], dtype=torch.float64)
    y = torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64)
    expected = -(2 * math.log(0.8) + math.log(0.6)) / 4
    torch.testing.assert_close(observed_negatives_bce(f, t, y), torch.tensor(expected).double())
    weight = torch.tensor([2.0, 1.0, 1.0, 3.0], dtype=torch.float64)
    expected = -(3 * math.log(0.8) + 3 * math.log(0.6)) / 4
    torch.testing.assert_close(
        observed_negatives_bce(f, t, y, weight=weight), torch.tensor(expected).double()
    )
    # τ = 0 keeps every label: plain BCE
    torch.testing.assert_close(observed_negatives_bce(f, t, y, 0.0), binary_cross_entropy(f, y))


def test_observed_negatives_count_background_in_front_of_bone_whatever_t():
    f = torch.tensor([0.8, 0.8, 0.4, 0.4], dtype=torch.float64)
    t = torch.tensor([0.05, 1.0, 0.29, 0.3], dtype=torch.float64)
    y = torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64)
    # the background label at T = 0.29 lies in front of its scanline's bone: it counts
    front = torch.tensor([False, False, True, False])
    expected = -(2 * math.log(0.8) + 2 * math.log(0.6)) / 4
    torch.testing.assert_close(
        observed_negatives_bce(f, t, y, in_front=front), torch.tensor(expected).double()
    )
    # a bone label or a lit background label marked in front counts as it did
    torch.testing.assert_close(
        observed_negatives_bce(f, t, y, in_front=torch.tensor([True, True, False, True])),
        observed_negatives_bce(f, t, y),
    )
    g = f.clone().requires_grad_()
    observed_negatives_bce(g, t, y, in_front=front).backward()
    assert g.grad[2] != 0
    for bad in (torch.tensor([True, False]), torch.tensor([1, 0, 1, 0])):
        with pytest.raises(UltronInputError, match="in_front"):
            observed_negatives_bce(f, t, y, in_front=bad)


def test_background_in_front_of_bone_trains_f_down_with_front_negatives_only():
    # bone where x0 > 0.5; background at x0 < -0.5, all with T = 0 (the field calls it
    # shadow) but in front of the bone: only the "front" negatives let it teach f "no bone"
    data = _separable_data()
    x0 = data.inputs[:, 0]
    keep = (x0 > 0.5) | (x0 < -0.5)
    labels = (x0[keep] > 0.5).to(torch.uint8)
    front = labels == 0
    dark = OccupancyTrainingData(
        data.inputs[keep], torch.zeros(int(keep.sum())), labels, in_front=front
    )
    probe = torch.tensor([[-0.8, 0.0, 0.0]])
    results = {}
    for negatives in ("front", "observed"):
        config = OccupancyTrainConfig(
            iters=300, batch_size=512, lr=1e-3, seed=1, network=SMALL, negatives=negatives
        )
        network, _ = fit_occupancy(dark, config)
        with torch.no_grad():
            results[negatives] = float(network.occupancy(probe))
    assert results["front"] < 0.1  # taught by the background in front
    assert results["observed"] > 0.5  # no negative counted: bone everywhere
    summary = dark.summary(0.3)
    assert summary["n_background_in_front"] == int(front.sum())
    assert summary["n_background_in_front_below_threshold"] == int(front.sum())


def test_observed_negatives_gradcheck_and_shadow():
    f = torch.rand(6, dtype=torch.float64).clamp(0.05, 0.95).requires_grad_()
    t = torch.tensor([0.0, 0.1, 0.5, 0.9, 0.2, 1.0], dtype=torch.float64)
    y = torch.tensor([0, 1, 0, 1, 0, 0], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a: observed_negatives_bce(a, t, y), (f,))
    observed_negatives_bce(f, t, y).backward()
    assert f.grad[0] == 0 and f.grad[4] == 0  # shadowed background: no gradient
    assert f.grad[1] != 0 and f.grad[2] != 0  # a bone label in shadow still counts


def test_observed_negatives_invalid_inputs():
    f = torch.full((3,), 0.5)
    with pytest.raises(UltronInputError, match="min_transmission"):
        observed_negatives_bce(f, torch.ones(3), torch.zeros(3), math.nan)
    with pytest.raises(UltronInputError, match="transmission"):
        observed_negatives_bce(f, torch.ones(2), torch.zeros(3))
    with pytest.raises(UltronInputError, match="negatives"):
        OccupancyTrainConfig(negatives="some")
    with pytest.raises(UltronInputError, match="observed_transmission"):
        OccupancyTrainConfig(observed_transmission=1.5)
    inputs, labels = torch.zeros(3, 2), torch.zeros(3, dtype=torch.uint8)
    with pytest.raises(UltronInputError, match="in_front"):
        OccupancyTrainingData(
            inputs, torch.ones(3), labels, in_front=torch.ones(2, dtype=torch.bool)
        )
    with pytest.raises(UltronInputError, match="in_front"):
        OccupancyTrainingData(inputs, torch.ones(3), labels, in_front=torch.ones(3))


def test_observed_negatives_train_through_shadow():
    # as test_compensated_loss_ignores_shadowed_negatives, with negatives="observed"
    data = _separable_data()
    shadow = data.inputs[:, 0] > 0.6
    labels = data.labels.clone()
    labels[shadow] = 0
    shadowed = OccupancyTrainingData(data.inputs, torch.where(shadow, 0.0, 1.0), labels)
    config = OccupancyTrainConfig(
        iters=300, batch_size=512, lr=1e-3, seed=1, network=SMALL, negatives="observed"
    )
    network, _ = fit_occupancy(shadowed, config)
    with torch.no_grad():
        assert float(network.occupancy(torch.tensor([[0.8, 0.0, 0.0]]))) > 0.5


def test_balanced_positive_weight():
    labels = torch.tensor([1.0] + [0.0] * 9)
    balanced = OccupancyTrainConfig(positive_weight=None)
    assert positive_class_weight(labels, balanced) == pytest.approx(9.0)
    assert positive_class_weight(torch.tensor([1.0] + [0.0] * 99), balanced) == 20.0
    assert positive_class_weight(labels, OccupancyTrainConfig(positive_weight=2.0)) == 2.0
    # the default is the paper's unweighted loss
    assert positive_class_weight(labels, OccupancyTrainConfig()) == 1.0


def test_positive_weight_parsing_and_validation():
    assert parse_positive_weight("balanced") is None
    assert parse_positive_weight("2.5") == 2.5
    for bad in ("0", "-1", "nan", "inf", "heavy"):
        with pytest.raises(UltronInputError, match="positive_weight"):
            parse_positive_weight(bad)
    with pytest.raises(UltronInputError, match="positive_weight"):
        OccupancyTrainConfig(positive_weight=float("nan"))


SMALL = OccupancyNetworkConfig(width=64, depth=4, skip_at=2, n_frequencies=2)


def _separable_data(
    n: int = 4000, transmission: torch.Tensor | None = None
) -> OccupancyTrainingData:
    generator = torch.Generator().manual_seed(0)
    inputs = torch.rand(n, 3, generator=generator) * 2 - 1
    labels = (inputs[:, 0] > 0.3).to(torch.uint8)
    transmission = torch.ones(n) if transmission is None else transmission
    return OccupancyTrainingData(inputs, transmission, labels)


def test_network_learns_a_separable_rule():
    data = _separable_data()
    config = OccupancyTrainConfig(
        iters=300, batch_size=512, lr=1e-3, loss="bce", seed=1, network=SMALL
    )
    network, log = fit_occupancy(data, config)
    assert log[-1]["loss"] < 0.5 * log[0]["loss"]
    with torch.no_grad():
        predicted = network.occupancy(data.inputs) > 0.5
    accuracy = (predicted == data.labels.bool()).float().mean()
    assert accuracy > 0.95


def test_occupancy_in_bfloat16_is_mixed_precision_and_float32_is_exact():
    network = OccupancyNetwork(SMALL)
    inputs = _separable_data(256).inputs
    exact = network.occupancy(inputs)
    assert torch.equal(occupancy_in(network, inputs, "float32"), exact)
    mixed = occupancy_in(network, inputs, "bfloat16")
    assert mixed.dtype == torch.float32 and not torch.equal(mixed, exact)
    # bfloat16 products: 8 bits of mantissa, a few parts in a thousand on f
    torch.testing.assert_close(mixed, exact, rtol=0, atol=2e-2)
    with pytest.raises(UltronInputError, match="precision"):
        occupancy_in(network, inputs, "float16")
    with pytest.raises(UltronInputError, match="precision"):
        OccupancyTrainConfig(precision="half")


def test_a_bfloat16_fit_learns_the_rule_and_keeps_float32_weights():
    data = _separable_data()
    config = OccupancyTrainConfig(iters=300, batch_size=512, lr=1e-3, loss="bce", seed=1,
                                  network=SMALL, precision="bfloat16")  # fmt: skip
    network, log = fit_occupancy(data, config)
    assert all(p.dtype == torch.float32 for p in network.parameters())
    assert log[-1]["loss"] < 0.5 * log[0]["loss"]
    with torch.no_grad():
        accuracy = ((network.occupancy(data.inputs) > 0.5) == data.labels.bool()).float().mean()
    assert accuracy > 0.95
    exact, _ = fit_occupancy(data, replace(config, precision="float32"))
    assert not torch.equal(network.trunk.output.weight, exact.trunk.output.weight)


def test_compensated_loss_ignores_shadowed_negatives():
    # the rule is x0 > 0.3, but points with x0 > 0.6 are labelled 0 in full shadow (T = 0):
    # the compensated loss must still predict bone there, plain BCE must not
    data = _separable_data()
    shadow = data.inputs[:, 0] > 0.6
    labels = data.labels.clone()
    labels[shadow] = 0
    transmission = torch.where(shadow, 0.0, 1.0)
    shadowed = OccupancyTrainingData(data.inputs, transmission, labels)
    probe = torch.tensor([[0.8, 0.0, 0.0]])
    results = {}
    for loss in ("ultron", "bce"):
        config = OccupancyTrainConfig(
            iters=300, batch_size=512, lr=1e-3, loss=loss, seed=1, network=SMALL,
            negatives="weighted",
        )  # fmt: skip
        network, _ = fit_occupancy(shadowed, config)
        with torch.no_grad():
            results[loss] = float(network.occupancy(probe))
    # measured f(0.8, 0, 0): compensated 0.68 / 0.99 / 0.75 at seeds 1 / 2 / 3, BCE < 1e-8
    assert results["bce"] < 0.01
    assert results["ultron"] > 0.5


def test_an_anchor_keeps_the_answer_where_no_label_is_and_the_labels_win_where_they_are():
    # a network trained on the rule x0 > 0.3 is fine-tuned on new labels that call the half
    # x1 < 0 all background; the anchor holds it, on the half x1 > 0, to its earlier answer
    data = _separable_data()
    config = OccupancyTrainConfig(iters=300, batch_size=512, lr=1e-3, loss="bce", seed=1,
                                  network=SMALL)  # fmt: skip
    trained, _ = fit_occupancy(data, config)
    lower = data.inputs[:, 1] < 0
    relabelled = OccupancyTrainingData(
        data.inputs[lower],
        torch.ones(int(lower.sum())),
        torch.zeros(int(lower.sum()), dtype=torch.uint8),
    )
    with torch.no_grad():
        before = trained.occupancy(data.inputs[~lower])
    anchor = OccupancyAnchor(data.inputs[~lower], before, weight=1.0)
    tune = replace(config, iters=150, seed=2)
    drift, bone_left = {}, {}
    for name, held in (("plain", None), ("anchored", anchor)):
        network, log = fit_occupancy(relabelled, tune, copy.deepcopy(trained), anchor=held)
        with torch.no_grad():
            drift[name] = float((network.occupancy(data.inputs[~lower]) - before).abs().mean())
            relabelled_bone = lower & (data.inputs[:, 0] > 0.3)
            bone_left[name] = float(
                (network.occupancy(data.inputs[relabelled_bone]) > 0.5).float().mean()
            )
        assert ("anchor" in log[-1]) == (held is not None)
    assert drift["anchored"] < 0.3 * drift["plain"]
    assert drift["plain"] > 0.1  # without the anchor the new labels spill over
    assert bone_left["plain"] < 0.1 and bone_left["anchored"] < 0.1  # the labels win (1 before)


def test_anchor_validation():
    inputs, targets = torch.zeros(4, 3), torch.full((4,), 0.5)
    for bad_inputs, bad_targets, weight, match in (
        (inputs, torch.zeros(3), 1.0, "do not match"),
        (torch.zeros(4), targets, 1.0, "do not match"),
        (torch.zeros(0, 3), torch.zeros(0), 1.0, "no anchor points"),
        (inputs, targets, -1.0, "anchor.weight"),
        (inputs, targets, math.nan, "anchor.weight"),
        (inputs, torch.full((4,), 1.5), 1.0, r"\[0, 1\]"),
    ):
        with pytest.raises(UltronInputError, match=match):
            OccupancyAnchor(bad_inputs, bad_targets, weight)


def test_training_is_deterministic():
    data = _separable_data(500)
    config = OccupancyTrainConfig(iters=20, batch_size=64, seed=3, network=SMALL)
    a, _ = fit_occupancy(data, config)
    b, _ = fit_occupancy(data, config)
    for pa, pb in zip(a.parameters(), b.parameters(), strict=True):
        assert torch.equal(pa, pb)


def test_log_and_progress_come_from_the_one_training_loop():
    data = _separable_data(500)
    config = OccupancyTrainConfig(iters=120, batch_size=64, seed=3, network=SMALL)
    reports: list[dict] = []
    _, log = fit_occupancy(data, config, progress=reports.append)
    assert [e["step"] for e in log] == [1, 50, 100, 120]  # first, every 50th, last
    assert reports == [{"iterations": 120, **entry} for entry in log]
    assert all(set(e) == {"step", "loss", "seconds"} for e in log)


def test_network_shapes_and_last_layers():
    network = OccupancyNetwork(OccupancyNetworkConfig(in_dim=3, n_frequencies=2))
    assert network(torch.zeros(5, 3)).shape == (5,)
    assert len(network.last_layers(2)) == 2
    with pytest.raises(UltronInputError, match="inputs"):
        network(torch.zeros(5, 4))


def test_encoded_inputs_pass_the_rest_through_unencoded():
    config = OccupancyNetworkConfig(in_dim=5, n_frequencies=2, encoded_inputs=2)
    network = OccupancyNetwork(config)
    # γ widens the 2 encoded inputs to 2·(2·2 + 1) = 10; the other 3 enter as they are
    assert network.trunk.hidden[0].in_features == 13
    x = torch.randn(4, 5, generator=torch.Generator().manual_seed(0))
    trunk_input = torch.cat([network.encoding(x[:, :2]), x[:, 2:]], dim=-1)
    assert torch.equal(network(x), network.trunk(trunk_input).squeeze(-1))
    # None (the default) encodes every input; a saved config round-trips
    assert OccupancyNetwork(OccupancyNetworkConfig(in_dim=5)).trunk.hidden[0].in_features == 45
    assert OccupancyNetworkConfig.from_dict(config.to_dict()) == config
    for bad in (-1, 6):
        with pytest.raises(UltronInputError, match="encoded_inputs"):
            OccupancyNetworkConfig(in_dim=5, encoded_inputs=bad)


def test_training_leaves_torch_global_rng_alone():
    data = _separable_data(200)
    config = OccupancyTrainConfig(iters=3, batch_size=64, seed=3, network=SMALL)
    torch.manual_seed(1234)
    expected = torch.rand(3)
    torch.manual_seed(1234)
    fit_occupancy(data, config)
    assert torch.equal(torch.rand(3), expected)
    # and the initial weights still come from the seed alone
    torch.manual_seed(99)
    a, _ = fit_occupancy(data, replace(config, iters=0))
    b, _ = fit_occupancy(data, replace(config, iters=0))
    assert all(torch.equal(x, y) for x, y in zip(a.parameters(), b.parameters(), strict=True))


class _ConstantOccupancy(torch.nn.Module):
    """f ≡ ``value`` for every input: a network whose loss is worked out by hand."""

    def __init__(self, value: float):
        super().__init__()
        self.value = torch.nn.Parameter(torch.tensor(value))

    def occupancy(self, inputs: torch.Tensor) -> torch.Tensor:
        return self.value.expand(inputs.shape[0])


def test_label_loss_by_hand():
    """f ≡ 0.8, T = 1 / 0.5 alternating, labels 1, 0, 0, 0 repeated: the compensated loss
    with weighted negatives is the mean of −log 0.8, −log(1 − 0.4), −log 0.2, −log(1 − 0.4);
    every second pixel (max_points n / 2) leaves −log 0.8 and −log 0.2; positive weight 3
    triples the bone term."""
    n = 8
    labels = torch.tensor([1.0, 0.0, 0.0, 0.0] * 2)
    transmission = torch.tensor([1.0, 0.5] * 4)
    data = OccupancyTrainingData(torch.zeros(n, 3), transmission, labels)
    config = OccupancyTrainConfig(loss="ultron", negatives="weighted", positive_weight=1.0)
    network = _ConstantOccupancy(0.8)
    every = -(math.log(0.8) + 2 * math.log(0.6) + math.log(0.2)) / 4
    assert label_loss(network, data, config) == pytest.approx(every, rel=1e-6)
    assert label_loss(network, data, config, max_points=4) == pytest.approx(
        -(math.log(0.8) + math.log(0.2)) / 2, rel=1e-6
    )
    weighted = replace(config, positive_weight=3.0)
    assert label_loss(network, data, weighted, chunk=3) == pytest.approx(
        -(3 * math.log(0.8) + 2 * math.log(0.6) + math.log(0.2)) / 4, rel=1e-6
    )
    plain = replace(config, loss="bce")  # T ignored: −log(1 − 0.8) for each background label
    assert label_loss(network, data, plain) == pytest.approx(
        -(math.log(0.8) + 3 * math.log(0.2)) / 4, rel=1e-6
    )
    with pytest.raises(ValueError, match="max_points"):
        label_loss(network, data, config, max_points=0)


def test_label_loss_ranks_a_fitted_network_below_an_untrained_one():
    data = _separable_data()
    config = OccupancyTrainConfig(iters=300, batch_size=512, lr=1e-3, loss="bce", seed=1,
                                  network=SMALL)  # fmt: skip
    trained, _ = fit_occupancy(data, config)
    untrained, _ = fit_occupancy(data, replace(config, iters=0))
    assert label_loss(trained, data, config) < 0.5 * label_loss(untrained, data, config)
