"""Settings of :mod:`egorelight_cli.stages.ik`: one field per ``stages/ik.yaml`` key, defaults
taken from that file (the one place they live), every value checked on construction against the
file's ``checks`` (the same rules ``--set`` meets)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from functools import partial

from egorelight_cli.config import check_settings, setting, settings_from_config
from egorelight_cli.errors import EgorelightError

_key = partial(setting, "ik")


@dataclass(frozen=True)
class IKSettings:
    """Everything the solver reads: one field per ``stages/ik.yaml`` key (``_key``), validated on
    construction (a bad value is a one-line error naming its config key)."""

    solver: str = _key("solver")
    fps: float = _key("fps")
    length_unit_m: float = _key("length_unit_m")
    w_data: float = _key("weights.data")
    w_temporal: float = _key("weights.temporal")
    w_hand_temporal: float = _key("weights.hand_temporal")
    w_reg: float = _key("weights.reg")
    w_dof_limit: float = _key("weights.dof_limit")
    min_confidence: float = _key("min_confidence")
    global_keypoints: tuple[str, ...] = _key("global_keypoints")
    body_stage_includes_root: bool = _key("body_stage_includes_root")
    regularise_root: bool = _key("regularise_root")
    project_limits: bool = _key("project_limits")
    lm_iterations: int = _key("lm.iterations")
    lm_tolerance: float = _key("lm.tolerance")
    lm_chunk_frames: int = _key("lm.chunk_frames")
    lm_frame_iterations: int = _key("lm.frame_iterations")
    lm_sweep_tolerance: float = _key("lm.sweep_tolerance")
    lm_coarse_step: int = _key("lm.coarse_step")
    lm_polish_iterations: int = _key("lm.polish_iterations")
    lbfgs_iterations: int = _key("lbfgs.iterations")
    lbfgs_history: int = _key("lbfgs.history")
    hand_components: int = _key("hand_pca.components")
    hand_samples: int = _key("hand_pca.synthetic_samples")
    hand_max_flexion_deg: float = _key("hand_pca.max_flexion_deg")
    robust_loss: str = _key("robust.loss")
    huber_delta_m: float = _key("robust.huber_delta_m")
    outlier_distance_m: float = _key("robust.outlier_distance_m")
    outlier_residual_factor: float = _key("robust.residual_factor")
    outlier_min_residual_m: float = _key("robust.min_residual_m")
    min_span_m: float = _key("robust.min_span_m")
    max_span_m: float = _key("robust.max_span_m")
    seed: int = _key("seed", 0)

    def __post_init__(self) -> None:
        check_settings(self)
        if not self.min_span_m < self.max_span_m:
            raise EgorelightError(f"ik robust.min_span_m ({self.min_span_m}) must be below robust.max_span_m "
                                  f"({self.max_span_m})")

    @classmethod
    def key(cls, name: str) -> str:
        """The config key (``lm.iterations``) of settings field ``name`` (``lm_iterations``)."""
        return next(f.metadata["key"] for f in fields(cls) if f.name == name)

    @classmethod
    def from_config(cls, cfg: Mapping) -> "IKSettings":
        """From a resolved ``ik`` stage config (see ``stages/ik.yaml``)."""
        return settings_from_config(cls, cfg)
