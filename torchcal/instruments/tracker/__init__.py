"""The tracker instrument (see :mod:`torchcal.instruments.tracker.plugin`)."""

from torchcal.instruments.tracker.plugin import TrackerInstrument

INSTRUMENT = TrackerInstrument()

__all__ = ["INSTRUMENT", "TrackerInstrument"]
