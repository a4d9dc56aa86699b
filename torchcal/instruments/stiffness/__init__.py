"""The stiffness instrument (see :mod:`torchcal.instruments.stiffness.plugin`)."""

from torchcal.instruments.stiffness.plugin import StiffnessInstrument

INSTRUMENT = StiffnessInstrument()

__all__ = ["INSTRUMENT", "StiffnessInstrument"]
