"""The studies ``evaluate.py`` can run, by the ``study:`` key of their config.

Each entry names the module that holds the study's config dataclass (a subclass of
`StudyConfig`) and its ``run(config, outputs)``. Modules are
imported on demand, so a study's optional dependencies are needed only when it runs.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from neuralmap.exceptions import NeuralMapError

__all__ = ["STUDIES", "StudySpec", "get_study"]


@dataclass(frozen=True)
class StudySpec:
    """Where a study lives.

    Attributes:
        module: Import path of the study module.
        config: Name of its config dataclass in that module.
        description: One line for ``--help`` and the report.
        default_config: File name of its shipped YAML under ``configs/``.
    """

    module: str
    config: str
    description: str
    default_config: str


#: Every study, by its ``study:`` key.
STUDIES: dict[str, StudySpec] = {
    "tan": StudySpec(
        "neuralmap.studies.tan", "TanStudyConfig",
        "Monte Carlo terrain-aided navigation: linearisation methods against the PCRB",
        "tan.yaml",
    ),
    "map_size": StudySpec(
        "neuralmap.studies.map_size", "MapSizeStudyConfig",
        "Stored bytes vs map error vs navigation accuracy: neural maps against compressed grids",
        "map_size.yaml",
    ),
    "acquisition": StudySpec(
        "neuralmap.studies.acquisition", "AcquisitionStudyConfig",
        "TAN acquisition from large initial errors: EKF, EKF bank, point mass, point mass -> EKF",
        "acquisition.yaml",
    ),
    "tan_outliers": StudySpec(
        "neuralmap.studies.tan_outliers", "TanOutliersConfig",
        "TAN under radar-altimeter faults: robust and adaptive update policies",
        "tan_outliers.yaml",
    ),
    "tan_scale": StudySpec(
        "neuralmap.studies.tan_scale", "TanScaleConfig",
        "TAN Monte Carlo at scale: chunked runs in bounded memory over worker processes",
        "tan_scale.yaml",
    ),
    "wind": StudySpec(
        "neuralmap.studies.wind", "WindStudyConfig",
        "Wind-field estimation: TVAR-model filters (KF, Sage-Husa, RAF, VB) against the LTI "
        "model, clean / outliers / shear, and track correction",
        "wind.yaml",
    ),
    "dem_errors": StudySpec(
        "neuralmap.studies.dem_errors", "DemErrorsStudyConfig",
        "DEM-related error models: identification, linearisation error m2, 5/6/7-state filters",
        "dem_errors.yaml",
    ),
    "gnss_ins": StudySpec(
        "neuralmap.studies.gnss_ins", "GnssInsStudyConfig",
        "Monte Carlo GNSS/MEMS-IMU loosely coupled navigation on an urban drive (paper 003)",
        "gnss_ins.yaml",
    ),
    "learned": StudySpec(
        "neuralmap.studies.learned", "LearnedStudyConfig",
        "Differentiable TAN: learned Q/R and refined map against hand-tuned, consistent and "
        "variational filters; EM anchor",
        "learned.yaml",
    ),
    "flight": StudySpec(
        "neuralmap.studies.flight", "FlightStudyConfig",
        "Navigate a recorded flight: terrain-aided fixes with covariance and status over a "
        "DEM or a trained map, errors against the log's reference",
        "flight.yaml",
    ),
}


def get_study(name: str) -> tuple[type[Any], Callable[..., Any], StudySpec]:
    """The config class, ``run`` function and spec of the study ``name``.

    Raises:
        NeuralMapError: No such study.
    """
    spec = STUDIES.get(name)
    if spec is None:
        raise NeuralMapError(
            f"study: unknown study {name!r}; known: {', '.join(sorted(STUDIES))} "
            "(the 'study:' key of the config picks one)."
        )
    module = importlib.import_module(spec.module)
    return getattr(module, spec.config), module.run, spec
