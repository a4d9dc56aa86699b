"""The profile instrument (see :mod:`torchcal.instruments.profile.plugin`)."""

from torchcal.instruments.profile.plugin import ProfileInstrument

INSTRUMENT = ProfileInstrument()

__all__ = ["INSTRUMENT", "ProfileInstrument"]
