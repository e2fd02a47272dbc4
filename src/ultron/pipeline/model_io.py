"""A run's trained network on disk: ``DIR/network.pt`` (atomic), for fine-tuning and reuse.

The file is a ``torch.save`` of plain data only (loaded with ``weights_only=True``)::

    {"format": "ultron-network/1",
     "kind": "OccupancyNetwork" | "SDFNetwork",
     "config": {...architecture...},
     "state_dict": {...},
     "meta": {"method": ..., "input": "theta" | "unit_cube" | ..., ...}}

``meta`` says what the network's input is: UltrON's f_ω takes θ normalised with the acoustic
field's statistics (``theta_channels`` names their order); ON takes the unit-cube position.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ultron import atomic
from ultron.errors import UltronInputError, malformed_entries
from ultron.fields.occupancy import OccupancyNetwork, OccupancyNetworkConfig
from ultron.fields.sdf import SDFNetwork, SDFNetworkConfig
from ultron.models.fitted import check_finite_weights

NETWORK_FILE = "network.pt"
NETWORK_FORMAT = "ultron-network/1"


def _network_classes() -> dict[str, tuple[type, type]]:

    return {
        "OccupancyNetwork": (OccupancyNetwork, OccupancyNetworkConfig),
        "SDFNetwork": (SDFNetwork, SDFNetworkConfig),
    }


def save_network(out_dir: str | Path, network: nn.Module, meta: dict[str, Any]) -> Path:
    """Atomically write ``out_dir/network.pt`` with the network's config, weights and ``meta``."""
    kind = type(network).__name__
    if kind not in _network_classes():
        raise UltronInputError("network", "kind", f"cannot save a {kind}")
    payload = {
        "format": NETWORK_FORMAT,
        "kind": kind,
        "config": network.config.to_dict(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in network.state_dict().items()},
        "meta": dict(meta),
    }
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    path = Path(out_dir) / NETWORK_FILE
    atomic.write_bytes(path, buffer.getvalue())
    return path


def load_network(model_dir: str | Path) -> tuple[nn.Module, dict[str, Any]]:
    """The network saved in ``model_dir`` (eval mode) and its ``meta``; clear errors otherwise."""
    path = Path(model_dir) / NETWORK_FILE
    if not Path(model_dir).is_dir():
        raise UltronInputError(str(model_dir), "MODEL_DIR", "no such directory")
    if not path.is_file():
        raise UltronInputError(
            str(path), NETWORK_FILE, "missing: MODEL_DIR must be the output of a reconstruct run "
            "of a learned method (e.g. --method ultron)",
        )  # fmt: skip
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # a truncated or foreign file: torch's message runs to lines
        raise UltronInputError(
            str(path), NETWORK_FILE, f"cannot be read ({type(error).__name__}): not a network"
            " ultron saved, or damaged; run reconstruct again to write it",
        ) from None  # fmt: skip
    if not isinstance(payload, dict) or payload.get("format") != NETWORK_FORMAT:
        raise UltronInputError(str(path), "format", f"expected {NETWORK_FORMAT!r}")
    classes = _network_classes()
    if payload.get("kind") not in classes:
        raise UltronInputError(
            str(path), "kind", f"expected one of {tuple(classes)}, got {payload.get('kind')!r}"
        )
    network_class, config_class = classes[payload["kind"]]
    for key, required in (("config", True), ("state_dict", True), ("meta", False)):
        value = payload.get(key) if required else payload.get(key, {})
        if not isinstance(value, dict):
            raise UltronInputError(str(path), key, f"expected an object, got {value!r:.60}")
    with malformed_entries(path, "config"):
        network = network_class(config_class(**payload["config"]))
    try:
        network.load_state_dict(payload["state_dict"])
    except (RuntimeError, TypeError, ValueError) as error:
        first = str(error).strip().splitlines()
        detail = " ".join(line.strip() for line in first[:2])[:200]
        raise UltronInputError(
            str(path), "state_dict", f"does not fit its config ({detail})"
        ) from None
    check_finite_weights(network, path, "state_dict")
    network.eval()
    return network, dict(payload.get("meta", {}))
