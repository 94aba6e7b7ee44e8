"""The ``flight`` study: navigate one recorded flight, as ``neuralmap-navigate`` does.

``python evaluate.py --config configs/flight.yaml --log LOG --map MAP`` runs the product's
flight navigation (`neuralmap.flights.flight`: `navigate_flight`, then `write_flight`) with a
study's outputs (report.md, results.json, figures, TensorBoard, config.yaml).
"""

from __future__ import annotations

from dataclasses import dataclass

from neuralmap.flights.flight import FlightOptions, navigate_flight, write_flight
from neuralmap.outputs import StudyOutputs
from neuralmap.studies.base import StudyConfig

__all__ = ["FlightStudyConfig", "run"]


@dataclass
class FlightStudyConfig(StudyConfig, FlightOptions):
    """Options of the flight study: the study's (`StudyConfig`) and the flight's
    (`neuralmap.flights.flight.FlightOptions`)."""

    study: str = "flight"
    experiment: str = "flight"
    threads: int | None = 1

    def validate(self) -> None:
        """Checks the study's and the flight's options."""
        StudyConfig.validate(self)
        FlightOptions.validate(self)


def run(config: FlightStudyConfig, outputs: StudyOutputs) -> None:
    """Navigates the flight and writes its outputs (`navigate_flight`,
    `write_flight`)."""
    write_flight(navigate_flight(config, outputs=outputs), outputs)
