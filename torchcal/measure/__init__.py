"""Instrument models: laser tracker, multi-station laser tracer (self-calibrating multilateration)."""

from torchcal.measure.base import Instrument, joint_columns
from torchcal.measure.lengths import LengthSigma, station_distances, tracer_lengths
from torchcal.measure.tracer import MultilaterationResult, multilaterate, predict_covariance
from torchcal.measure.tracer_instrument import TracerInstrument, length_columns
from torchcal.measure.tracer_plan import TracerPlan, plan_tracer_setup
from torchcal.measure.tracker import TrackerInstrument

INSTRUMENTS: dict[str, type[Instrument]] = {
    TrackerInstrument.name: TrackerInstrument,
    TracerInstrument.name: TracerInstrument,
}

__all__ = [
    "INSTRUMENTS",
    "Instrument",
    "LengthSigma",
    "MultilaterationResult",
    "TrackerInstrument",
    "TracerInstrument",
    "TracerPlan",
    "joint_columns",
    "length_columns",
    "multilaterate",
    "plan_tracer_setup",
    "predict_covariance",
    "station_distances",
    "tracer_lengths",
]
