"""The ``model`` artifact payload: a trained network (or fitted model) with its provenance.

A model artifact directory holds ``model.pt`` (``{"stage", "architecture", "state_dict",
"extra"}`` saved with ``torch.save``; loaded with ``weights_only=True``), ``curve.json`` (the
training curve: a list of ``{"step": int, <loss name>: float, ...}``) and ``curve.png``.
The resolved training config is in the artifact's manifest.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from egorelight_cli.errors import EgorelightError

MODEL_FILE = "model.pt"
CURVE_JSON = "curve.json"
CURVE_PNG = "curve.png"


@dataclass
class ModelPayload:
    """What a model artifact holds.

    Attributes:
        stage: the stage that trained it (``egopose``, ``egodepth``, ...).
        architecture: JSON-able constructor arguments of the network.
        state_dict: tensors (CPU).
        extra: JSON-able or tensor extras (normalisation constants, fitted PCA, ...).
        curve: training curve rows.
    """

    stage: str
    architecture: dict[str, Any]
    state_dict: dict[str, torch.Tensor]
    extra: dict[str, Any] = field(default_factory=dict)
    curve: list[dict[str, float]] = field(default_factory=list)


def write_model(root: str | Path, payload: ModelPayload, curve_title: str | None = None) -> list[Path]:
    """Write ``model.pt``, ``curve.json`` and ``curve.png`` into directory ``root``."""
    from egorelight_cli.io.images import write_image
    from egorelight_cli.render.plots import curve_plot

    root = Path(root)
    state = {k: v.detach().cpu().contiguous() for k, v in payload.state_dict.items()}
    torch.save({"stage": payload.stage, "architecture": payload.architecture, "state_dict": state,
                "extra": payload.extra}, root / MODEL_FILE)
    (root / CURVE_JSON).write_text(json.dumps(payload.curve, indent=1) + "\n")
    write_image(root / CURVE_PNG, curve_plot(payload.curve, curve_title or f"{payload.stage} training"))
    return [root / MODEL_FILE, root / CURVE_JSON, root / CURVE_PNG]


def read_model(root: str | Path, stage: str | None = None) -> ModelPayload:
    """Read a model payload directory; ``stage`` checks which stage trained it."""
    root = Path(root)
    path = root / MODEL_FILE
    if not path.is_file():
        raise EgorelightError("model file not found", path)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises pickle/zip/runtime errors for corrupt files (messages of many lines)
        first = (str(exc).strip().splitlines() or [""])[0]
        raise EgorelightError(f"cannot load model ({type(exc).__name__}: {first})", path) from None
    if not isinstance(data, dict) or "state_dict" not in data:
        raise EgorelightError("not an egorelight model file", path)
    if stage is not None and data.get("stage") != stage:
        raise EgorelightError(f"model was trained for stage {data.get('stage')!r}, not {stage!r}", path)
    curve = json.loads((root / CURVE_JSON).read_text()) if (root / CURVE_JSON).is_file() else []
    return ModelPayload(stage=data["stage"], architecture=data.get("architecture", {}), state_dict=data["state_dict"],
                        extra=data.get("extra", {}), curve=curve)
