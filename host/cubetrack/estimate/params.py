"""The estimate stage's parameters: the ``[estimator]`` section of the tracker config."""

from __future__ import annotations

from dataclasses import dataclass

from cubetrack.core.params import check_positive, param


@dataclass(frozen=True, slots=True)
class EstimatorParams:
    """Estimator thresholds; the ``[estimator]`` TOML table maps 1:1 onto these fields."""

    max_reprojection_error_px: float = param(
        3.0, "a single-marker PnP solution whose RMS reprojection error exceeds this is dropped, pixels",
    )
    corner_noise_px: float = param(
        0.5, "assumed corner noise (1 sigma), pixels: weighs reprojection error against the "
        "upright prior when choosing a face and an IPPE solution",
    )
    use_upright_prior: bool = param(
        True, "assume a floor body's cube (layout motion = \"floor\") stands upright: its z axis near "
        "world up. A free body (motion = \"free\") never has it, unless faces share an id: then it "
        "is what tells them apart; with distinct ids, false picks solutions by reprojection error alone",
    )
    upright_sigma_deg: float = param(
        10.0, "spread (1 sigma) of the cube's tilt from world up in the upright prior, degrees",
    )
    upright_tolerance_deg: float = param(
        35.0, "a face/solution implying a cube tilted more than this from world up is rejected, degrees",
    )
    max_face_spread_m: float = param(
        0.25, "faces implying a cube centre farther than this from the largest face's are dropped, metres",
    )
    joint_pnp: bool = param(
        True, "refine one cube pose over all identified faces' corners (else: the largest face's pose)",
    )
    max_joint_reprojection_error_px: float = param(
        3.0, "a joint multi-face solution above this RMS reprojection error is rejected (then "
        "subsets one face smaller are tried, down to the largest face alone), pixels",
    )

    def __post_init__(self) -> None:
        check_positive(self, "max_reprojection_error_px", "corner_noise_px", "upright_sigma_deg",
                       "upright_tolerance_deg", "max_face_spread_m", "max_joint_reprojection_error_px")
