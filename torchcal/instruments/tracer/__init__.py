"""The tracer instrument (see :mod:`torchcal.instruments.tracer.plugin`)."""

from torchcal.instruments.tracer.plugin import TracerInstrument

INSTRUMENT = TracerInstrument()

__all__ = ["INSTRUMENT", "TracerInstrument"]
